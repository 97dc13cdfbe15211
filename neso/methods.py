"""The paper's methods as first-class controllers: one disturbance estimator each, same PD law.

=================  ==================================================================
``pd``             no disturbance compensation on the altitude axis
``pd_nn``          Neural-Lander style: f̂ = h(z), h trained on measured acceleration
                   residuals, no observer
``pd_eso``         ESO alone (the teacher)
``neural_observer``single pathway (Liu et al. 2023): the network replaces the extended
                   state, no online correction
``neural_eso``     the dual pathway with the base network
``neural_eso_tdr`` the dual pathway with the network after Total Disturbance Retraining
=================  ==================================================================

Each entry names the network *role* it needs (``base``, ``acceleration``, ``tdr``); the
caller supplies the networks by role.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from neso.estimator import DisturbanceEstimator, NeuralESO, NeuralEsoConfig, NeuralObserver
from neso.network import LipschitzMLP


@dataclass(frozen=True, slots=True)
class MethodSpec:
    pathway: str  # pathway of the Neural-ESO, or "neural_observer"
    network_role: str | None
    description: str


METHODS: dict[str, MethodSpec] = {
    "pd": MethodSpec("none", None, "PD, no disturbance estimate"),
    "pd_nn": MethodSpec("nn", "acceleration", "PD + network on acceleration residuals (Neural-Lander)"),
    "pd_eso": MethodSpec("eso", None, "PD + ESO"),
    "neural_observer": MethodSpec("neural_observer", "base", "single-pathway neural observer (Liu et al. 2023)"),
    "neural_eso": MethodSpec("neural_eso", "base", "Neural-ESO, base network"),
    "neural_eso_tdr": MethodSpec("neural_eso", "tdr", "Neural-ESO after Total Disturbance Retraining"),
}


def build_estimator(
    method: str, config: NeuralEsoConfig, networks: dict[str, LipschitzMLP]
) -> DisturbanceEstimator:
    """A fresh estimator for ``method``; ``networks`` maps role → network."""
    try:
        spec = METHODS[method]
    except KeyError:
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(METHODS)}") from None
    network = None
    if spec.network_role is not None:
        if spec.network_role not in networks:
            raise ValueError(f"method {method!r} needs a {spec.network_role!r} network")
        network = networks[spec.network_role]
    if spec.pathway == "neural_observer":
        return NeuralObserver(config, network)
    return NeuralESO(replace(config, pathway=spec.pathway), network)
