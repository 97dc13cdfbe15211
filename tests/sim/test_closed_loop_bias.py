"""Issue 32: a network retrained on a flight's measured state finds the loop, not the disturbance. On the
lemniscate at constant height the state moves only because the loop answers the disturbance (a push up raises the
vehicle until the observer catches it), so a regression on it learns positive slopes in p_z and v_z: extra
feedback gain. Trained on the reference (z*, ż*: an instrument the disturbance does not move) the same data gives
no such slope — there is nothing exogenous to learn from at constant height, and the trainer says so (validation
loss that of predicting the mean)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from neso.learning import RECIPES, identify_thrust_lag, recipe_blocks
from neso.training import train_lipschitz_mlp
from neso.features import feature_set
from sim.experiments import PaperConfig, training_pairs
from sim.flights import FlightTask, run_flight

RECIPE = RECIPES["certified"]


@pytest.fixture(scope="module")
def flights():
    cfg = PaperConfig()
    est = cfg.estimator_config()
    teacher = [run_flight(FlightTask("nominal_landing", "pd_eso", {}, s, cfg.landing, est, cfg.control))
               for s in (500, 501)]
    lag = identify_thrust_lag([t.series() for t in teacher]).lag
    bound = cfg.base_bound(RECIPE)
    base = _train(*training_pairs(teacher, RECIPE.base_label, RECIPE.feature_set, lag, regressors="reference"),
                  bound, None)
    lem = replace(cfg.lemniscate, cycles=4)
    tdr_flight = run_flight(FlightTask("lemniscate_near_ground", "neural_eso", {"base": base.network}, 900, lem, est,
                                       cfg.control))
    return base, tdr_flight, lag, lem, bound


def _train(z, y, bound, init):
    blocks, block_bounds = recipe_blocks(RECIPE, feature_set(RECIPE.feature_set), bound)
    return train_lipschitz_mlp(z, y, lipschitz_bound=bound, bound_units="physical", epochs=40, seed=0, init=init,
                               scalers="fit", blocks=blocks, block_bounds=block_bounds,
                               metadata={"feature_set": RECIPE.feature_set})


def test_the_state_finds_the_loop_and_the_reference_does_not(flights):
    base, tdr_flight, lag, lem, bound = flights
    out = {}
    for regressors in ("state", "reference"):
        z, y = training_pairs([tdr_flight], RECIPE.tdr_label, RECIPE.feature_set, lag, skip_s=lem.cycle_start_s,
                              regressors=regressors)
        out[regressors] = _train(z, y, bound, base.network)
    moved = {k: {c: r.slopes[c] - base.slopes[c] for c in ("pos_z_m", "vel_z_mps")} for k, r in out.items()}
    print({k: {c: round(v, 3) for c, v in m.items()} for k, m in moved.items()},
          {k: round(r.val_loss_vs_mean, 3) for k, r in out.items()})
    # the loop's signature: both slopes pushed up, a stiffer and more damped loop
    assert moved["state"]["pos_z_m"] > 0.5 and moved["state"]["vel_z_mps"] > 0.2
    # on the instrument nothing pushes them up, and nothing is learned that held-out runs confirm
    assert moved["reference"]["pos_z_m"] < 0.1 and moved["reference"]["vel_z_mps"] < 0.1
    assert out["reference"].val_loss_vs_mean > 0.95
