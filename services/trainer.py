"""``trainer``: trains a network on recorded flights, certifies it, stores it, offers it to the estimator.

One per vehicle. Training runs in a worker thread of this process (never in the control loop's
processes; torch is imported here only), one job at a time, so the node keeps answering health
and commands while it trains. Commands on ``neso/<v>/cmd/trainer``:

- ``train {recordings?, mode?, label?, lipschitz_bound?, epochs?, offer?, force_offer?, seed?}``:
  queue a job; the reply says the job number at once. ``recordings``: ``.rrd`` paths (default:
  the newest one in ``--recordings-dir``, which may be the flight still being recorded: it is
  read up to its last flush). ``mode``: ``tdr`` (default: warm-started from the network the
  estimator flies, with its inputs and the label and normalisation of its recipe,
  :mod:`neso.learning`) or ``base`` (from scratch on ESO-teacher flights, the default recipe).
  ``label``: overrides the recipe's (``eso``, ``tdr``, ``applied``). ``lipschitz_bound``: in the
  recipe's units (default: for physical recipes the largest bound the certificate allows for the
  gains the vehicle flies, as the estimator reports them, times the recipe's fraction; for the
  paper's, the active network's L_N); ``epochs`` (100); ``offer`` (true: send the result to the
  estimator's gate); ``force_offer`` (offer even when predicted to fly worse or when it learned nothing); ``seed`` (0).

Before it offers, the trainer flies the recorded flights again in closed loop
(:mod:`sim.counterfactual`: the recorded reference, the disturbance reconstructed from the
recording injected, the vehicle's recorded mass and the thrust delay and lag identified on the same
recordings, whatever the label) with the active network, with the candidate, with PD+ESO at the flown
gains and with PD+ESO at the flown gains plus the candidate's slopes as gain
(:func:`neso.learning.equivalent_gains`), all on the same conditions: the predicted z RMSE change, and how
much of the candidate's gain over PD+ESO its gain alone gives and how much is learned disturbance, go with
the offer, into the registry and onto the dashboard. A candidate predicted to fly worse than the active
network, or no better than PD+ESO at the flown gains, or whose validation loss is not below that of predicting
the mean (it learned nothing), is stored but not offered unless ``force_offer``.
- ``status``: what the worker is doing and the last result.

A retried ``train`` is queued once (the node answers a repeated request id with the first answer).

Each job ends with an event ``job <n> done: …`` (network id, registry path, val loss, bounds,
small-gain verdict, stage times, the estimator's answer to the offer) or ``job <n> failed: …``.
What the active network is comes from the estimator's ``NetworkMsg``.
"""
from __future__ import annotations

import argparse
import glob
import math
import os
import queue
import time
from dataclasses import dataclass, field

from neso.control import ControlConfig
from neso.learning import LABELS
from neso.types import OMEGA_O_RPS
from recordings.layout import RECORDINGS_DIR
from runtime.options import add_options, config_from_options, option
from services.registry import DEFAULT_ROOT
from runtime.schema import NetworkMsg

MODES = ("tdr", "base")


@dataclass(frozen=True)
class TrainerConfig:
    """``kp``, ``kd``, ``omega_o_rps``: the gains the certificate is computed for until the
    estimator reports the ones flown."""

    registry: str = option(DEFAULT_ROOT, help="network registry root")
    recordings_dir: str = option(RECORDINGS_DIR, help="where recordings are looked for")
    kp: float = option(ControlConfig().kp[2], unit="1/s²", help="controller z gain k_p for the certificate")
    kd: float = option(ControlConfig().kd[2], unit="1/s", help="controller z gain k_d for the certificate")
    omega_o_rps: float = option(OMEGA_O_RPS, flag="--omega-o", unit="rad/s", help="observer bandwidth for the certificate")
    epochs: int = 100


@dataclass(frozen=True)
class Job:
    """One training request, validated."""

    number: int
    recordings: tuple[str, ...]
    mode: str
    label: str | None
    lipschitz_bound: float | None
    epochs: int
    offer: bool
    seed: int
    force_offer: bool = False


@dataclass
class JobResult:
    """What a finished job made. ``timings_s``: stage → seconds; ``offer``: (accepted, estimator's message)."""

    job: Job
    network_id: str = ""
    path: str = ""
    info: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    offer: tuple[bool, str] | None = None
    predicted: dict = field(default_factory=dict)

    def summary(self) -> str:
        i = self.info
        cert = i.get("certificate", {})
        times = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings_s.items())
        offer = "" if self.offer is None else (f"; offer {'accepted' if self.offer[0] else 'REFUSED'}: "
                                               f"{self.offer[1]}")
        from sim.counterfactual import prediction_text

        pred = f"; on the recorded flight(s): {prediction_text(self.predicted)}" if "change" in self.predicted else ""
        return (f"{self.network_id} at {self.path}: {i.get('n_samples')} {i.get('label')} samples "
                f"({i.get('feature_set')}, {i.get('mass_kg', float('nan')):g} kg; {i.get('thrust_response', '')}) "
                f"from {len(self.job.recordings)} recording(s), {learned_text(i, cert.get('kp'), cert.get('kd'))}, "
                f"certified L_N {i.get('certified_phys'):.4g} physical; {cert.get('text', '')}{pred}; {times}{offer}")


def learned_text(info: dict, kp: float | None = None, kd: float | None = None) -> str:
    """What a network learned, in one phrase: validation against the mean, the physical slopes and the slopes on
    p_z and v_z as a change of the z gains (``kp``, ``kd``: the flown gains, to say what they become)."""
    from neso.learning import equivalent_gains

    vs = info.get("val_loss_vs_mean")
    vs_text = f"val loss {vs:.3f} × the mean's" if isinstance(vs, float) and math.isfinite(vs) else "val loss unknown"
    slopes = info.get("slopes") or {}
    slope_text = ", ".join(f"{k} {v:+.3g}" for k, v in slopes.items())
    gain = equivalent_gains(slopes)
    gain_text = f"; as gain {gain.text(kp, kd)}" if gain is not None else ""
    return f"{vs_text}; slopes ∂f_N/∂input: {slope_text or 'none'}{gain_text}"


def parse_job(number: int, args: dict, config: TrainerConfig) -> Job:
    """A :class:`Job` from command args; ``ValueError`` naming what is wrong."""
    unknown = set(args) - {"recordings", "mode", "label", "lipschitz_bound", "epochs", "offer", "force_offer", "seed"}
    if unknown:
        raise ValueError(f"unknown train args {sorted(unknown)}")
    recordings = args.get("recordings")
    if recordings is None or recordings == []:
        found = sorted(glob.glob(os.path.join(config.recordings_dir, "**", "*.rrd"), recursive=True),
                       key=os.path.getmtime)
        if not found:
            raise ValueError(f"no recordings given and none in {config.recordings_dir}")
        recordings = [found[-1]]
    if isinstance(recordings, str):
        recordings = [recordings]
    if not isinstance(recordings, list) or not all(isinstance(r, str) and r for r in recordings):
        raise ValueError("recordings must be a list of .rrd paths")
    missing = [r for r in recordings if not os.path.isfile(r)]
    if missing:
        raise ValueError(f"no such recording(s): {missing}")
    mode = args.get("mode", "tdr")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    label = args.get("label")
    if label is not None and label not in LABELS:
        raise ValueError(f"label must be one of {LABELS}, got {label!r}")
    bound = args.get("lipschitz_bound")
    if bound is not None and not (isinstance(bound, (int, float)) and not isinstance(bound, bool) and 0 < bound < 1e3):
        raise ValueError(f"lipschitz_bound must be a number in (0, 1000), got {bound!r}")
    epochs = args.get("epochs", config.epochs)
    if not (isinstance(epochs, int) and not isinstance(epochs, bool) and 1 <= epochs <= 10_000):
        raise ValueError(f"epochs must be an integer in [1, 10000], got {epochs!r}")
    offer, force_offer = args.get("offer", True), args.get("force_offer", False)
    if not (isinstance(offer, bool) and isinstance(force_offer, bool)):
        raise ValueError("offer and force_offer must be true or false")
    seed = args.get("seed", 0)
    if not (isinstance(seed, int) and not isinstance(seed, bool)):
        raise ValueError("seed must be an integer")
    return Job(number, tuple(os.path.abspath(r) for r in recordings), mode, label,
               None if bound is None else float(bound), epochs, offer, seed, force_offer)


def active_network(active: dict):
    """The network the estimator flies, from ``NetworkMsg.active`` (its file, scaled to its certified L_N)."""
    from neso.netfile import load_network

    path = active.get("path", "")
    if not path or not os.path.isfile(path):
        raise ValueError(f"the active network {active.get('id')!r} has no file to warm-start from ({path!r})")
    net = load_network(path, expected_outputs=1)
    flown = float(active.get("certified_state", net.certified_lipschitz_state()))
    return net.scaled_to_bound(flown, "physical") if flown < net.certified_lipschitz_state() * (1 - 1e-9) else net


def flown_gains(certificate: dict | None, config: TrainerConfig) -> tuple[float, float, float]:
    """(k_p, k_d, ω_o) of the z axis as the estimator reports them flown, else the configured ones."""
    c = certificate or {}
    values = [c.get("kp"), c.get("kd"), c.get("omega_o")]
    if all(isinstance(v, (int, float)) and v > 0 for v in values):
        return tuple(float(v) for v in values)
    return config.kp, config.kd, config.omega_o_rps


def flown_mass(certificate: dict | None, recorded_kg: float) -> float:
    """The vehicle mass (kg) the estimator reports flying, else the recordings' own."""
    mass = (certificate or {}).get("vehicle_mass_kg")
    return float(mass) if isinstance(mass, (int, float)) and mass > 0 else float(recorded_kg)


def train_job(job: Job, config: TrainerConfig, vehicle: str, active: dict | None, offer_fn=None,
              certificate: dict | None = None) -> JobResult:
    """Dataset → training → certificate → closed-loop prediction → registry → offer
    (``offer_fn(path, predicted) -> (ok, message)``). ``active``/``certificate``: the estimator's
    latest ``NetworkMsg.active`` / ``.certificate``."""
    from flight.estimator import network_certificate
    from neso.certificate import LoopPlant
    from neso.features import feature_set
    from neso.types import VehicleModel
    from neso.learning import DEFAULT_RECIPE, RECIPES, recipe_blocks, recipe_bound, recipe_of
    from neso.training import train_lipschitz_mlp
    from recordings.dataset import load_training_set
    from services import registry

    result = JobResult(job)
    t0 = time.perf_counter()
    kp, kd, omega_o = flown_gains(certificate, config)
    init = None
    parent = ""
    if job.mode == "tdr":
        if not active:
            raise ValueError("tdr retrains the active network, and no estimator has reported one (none on the bus?); "
                             "mode base trains one from scratch (neso train --base)")
        init = active_network(active)
        parent = str(active.get("id", ""))
        recipe = recipe_of(init.metadata)
        label, fset = job.label or recipe.tdr_label, init.feature_set.key
    else:
        recipe = RECIPES[DEFAULT_RECIPE]
        label, fset = job.label or recipe.base_label, recipe.feature_set
    lag = init.thrust_lag if init is not None and init.feature_set.uses_applied_thrust else None
    ts = load_training_set(list(job.recordings), label, feature_set_key=fset, lag=lag, regressors=recipe.regressors)
    if ts.vehicle and ts.vehicle != vehicle:
        raise ValueError(f"the recordings are of vehicle {ts.vehicle!r}, this trainer serves {vehicle!r}")
    t1 = time.perf_counter()
    result.timings_s["dataset"] = t1 - t0
    mass_kg = flown_mass(certificate, ts.mass_kg)
    if job.lipschitz_bound is not None:
        bound = job.lipschitz_bound
    elif recipe.bound_units == "normalised" and init is not None:
        bound = init.lipschitz_bound
    else:
        from services.certificate_cache import adopt_budgets, keep_budgets

        adopt_budgets()  # found before on this machine: verified (~0.6 s) instead of bisected (~10 s)
        bound = recipe_bound(recipe, kp, kd, omega_o, mass_kg)
        keep_budgets()
    blocks, block_bounds = recipe_blocks(recipe, feature_set(ts.feature_set), bound)
    res = train_lipschitz_mlp(
        ts.z, ts.y_mps2, lipschitz_bound=bound, bound_units=recipe.bound_units, epochs=job.epochs, seed=job.seed,
        init=init, scalers=recipe.tdr_scalers if init is not None else "fit", blocks=blocks, block_bounds=block_bounds,
        metadata={"vehicle": vehicle, "parent": parent, "feature_set": ts.feature_set, "recipe": recipe.name,
                  "label": label, "thrust_lag_s": repr(ts.thrust_lag.time_constant_s),
                  "thrust_delay_s": repr(ts.thrust_lag.delay_s), "mass_kg": repr(float(ts.mass_kg)),
                  "regressors": ts.regressors})
    t2 = time.perf_counter()
    result.timings_s["train"] = t2 - t1
    plant = LoopPlant.of(ControlConfig(vehicle=VehicleModel(mass_kg=mass_kg)))
    cert = network_certificate(res.network, kp, kd, omega_o, plant).to_dict()
    t3 = time.perf_counter()
    result.timings_s["certify"] = t3 - t2
    if init is not None:
        result.predicted = predict_closed_loop(job.recordings, init, res.network, ts.thrust_lag, kp, kd, omega_o)
        result.timings_s["predict"] = time.perf_counter() - t3
    t4 = time.perf_counter()
    entry = registry.store(res.network, root=config.registry, vehicle=vehicle, label=label, parent=parent,
                           recordings=list(job.recordings), certificate=cert, predicted=result.predicted)
    result.network_id, result.path = entry.id, os.path.abspath(entry.path)
    lag = ts.thrust_lag
    result.info = dict(entry.info, n_samples=len(ts.y_mps2), feature_set=ts.feature_set, mass_kg=ts.mass_kg,
                       thrust_response=(f"thrust lag {lag.time_constant_s * 1e3:.1f} ms + delay {lag.delay_s * 1e3:.1f} "
                                        f"ms, {ts.lag_source}"))
    result.timings_s["store"] = time.perf_counter() - t4
    if job.offer and offer_fn is not None:
        withheld = withheld_because(res.val_loss_vs_mean, result.predicted, job.force_offer)
        if withheld:
            result.offer = (False, withheld)
        else:
            t5 = time.perf_counter()
            result.offer = offer_fn(result.path, result.predicted)
            result.timings_s["offer"] = time.perf_counter() - t5
    return result


def withheld_because(val_loss_vs_mean: float, predicted: dict, force_offer: bool) -> str:
    """Why a candidate is not offered (empty: offer it). One whose validation loss is not below that of
    predicting the mean learned nothing; one predicted (``predicted``: :func:`predict_closed_loop`'s) to fly worse
    than the active network, or no better than PD+ESO at the flown gains: none is offered unless ``force_offer`` (an
    operator trying the swap itself; the estimator's certificate gate and the canary still decide). One whose
    validation loss is not finite (training diverged) never is."""
    if not math.isfinite(val_loss_vs_mean):
        return f"not offered: its validation loss is {val_loss_vs_mean} (training diverged); force_offer does not change that"
    if force_offer:
        return ""
    if not val_loss_vs_mean < 1.0:
        return (f"not offered: its validation loss is {val_loss_vs_mean:.3f} × that of predicting the mean (it learned "
                "nothing the observer does not already remove); train with force_offer=true to offer it anyway")
    change, vs_pdeso = predicted.get("change"), predicted.get("change_vs_pdeso")
    if isinstance(change, float) and change >= 0:
        return (f"not offered: predicted to fly worse ({change * 100:+.0f} % z RMSE on the recorded flight); train with "
                "force_offer=true to offer it anyway")
    if isinstance(vs_pdeso, float) and vs_pdeso >= 0:
        return (f"not offered: predicted no better than PD+ESO at the flown gains ({vs_pdeso * 100:+.0f} % z RMSE on "
                "the recorded flight: not an improvement); train with force_offer=true to offer it anyway")
    return ""


def predict_closed_loop(recordings, active_net, candidate_net, lag, kp: float, kd: float, omega_o: float) -> dict:
    """Fly the recorded flights again (:mod:`sim.counterfactual`) with the active network, the candidate, PD+ESO at the
    flown z gains ``kp``, ``kd`` and ``omega_o``, and PD+ESO with the candidate's slopes added to the gains
    (:func:`neso.learning.equivalent_gains`). Besides :func:`sim.counterfactual.predict_change`'s figures:
    ``rmse_pdeso_cm``, ``change_vs_pdeso`` (candidate/PD+ESO − 1 on the recorded flight's level), ``gain_only``
    (the gains flown for it, or a ``note`` why none), ``rmse_gain_only_cm`` and, when the candidate beats PD+ESO,
    ``split``: of its gain over PD+ESO (``total_cm``) what its gain alone gives (``gain_cm``) and the rest
    (``learned_cm``), cm on the recorded flight's level."""
    from dataclasses import replace

    from neso.control import ControlConfig
    from neso.eso import EsoConfig
    from neso.estimator import NeuralESO, NeuralEsoConfig
    from neso.learning import equivalent_gains
    from recordings.conditions import recorded_conditions
    from recordings.reader import read_recording
    from sim.counterfactual import Variant, on_flight_cm, predict_change

    conditions = [c for path in recordings for c in recorded_conditions(read_recording(path), lag)]  # recorded masses
    if not conditions:
        return {}
    dt = conditions[0].dt_s

    def gains(kp_z: float, kd_z: float) -> ControlConfig:
        base = ControlConfig()
        return replace(base, kp=(*base.kp[:2], kp_z), kd=(*base.kd[:2], kd_z), dt_s=dt)

    est_cfg = NeuralEsoConfig(eso=EsoConfig(omega_o_rps=omega_o, dt_s=dt))
    pdeso = replace(est_cfg, pathway="eso")
    variants = {"active": Variant(lambda: NeuralESO(est_cfg, active_net), gains(kp, kd)),
                "candidate": Variant(lambda: NeuralESO(est_cfg, candidate_net), gains(kp, kd)),
                "pdeso": Variant(lambda: NeuralESO(pdeso), gains(kp, kd))}
    change = equivalent_gains(candidate_net.learned["slopes"])
    gain_only: dict = {"note": "its slopes on p_z and v_z are not recorded"} if change is None else {}
    if change is not None:
        kp2, kd2 = change.gains(kp, kd)
        gain_only = dict(change.to_dict(), kp=kp2, kd=kd2)
        if kp2 > 0 and kd2 > 0:
            variants["gain_only"] = Variant(lambda: NeuralESO(pdeso), gains(kp2, kd2))
        else:
            gain_only["note"] = f"its slopes as gain make k_p {kp2:.3g}, k_d {kd2:.3g}: not a PD controller to fly"
    out = predict_change(conditions, variants)
    out["gain_only"] = gain_only
    cand, pd = on_flight_cm(out, "candidate"), on_flight_cm(out, "pdeso")
    if pd > 0 and math.isfinite(pd):
        out["change_vs_pdeso"] = cand / pd - 1.0
    g = on_flight_cm(out, "gain_only") if "rmse_gain_only_cm" in out else None
    if g is not None and math.isfinite(g) and cand < pd:
        out["split"] = {"total_cm": pd - cand, "gain_cm": pd - g, "learned_cm": g - cand}
    return out


# -- bus adapter ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, TrainerConfig)


def run(args, bus) -> int:
    from runtime.client import ServiceUnavailable, command
    from runtime.node import Node, run_node

    os.nice(10)  # training shares the machine with the control loop: it yields the CPU to it
    config = config_from_options(TrainerConfig, args)
    node = Node("trainer", vehicle=args.vehicle, bus=bus, config=config)
    jobs: queue.Queue[Job] = queue.Queue()
    state = {"active": None, "certificate": None, "doing": "idle", "last": "", "next": 1}

    def on_network(msg: NetworkMsg, _received_s: float) -> None:
        state["active"] = dict(msg.active)
        state["certificate"] = dict(msg.certificate)

    def offer(path: str, predicted: dict) -> tuple[bool, str]:
        try:
            reply = command(node.session, node.keys, "estimator", "offer", {"path": path, "predicted": predicted},
                            timeout_s=5.0)
        except ServiceUnavailable as exc:
            return False, str(exc)
        return reply.ok, reply.message

    def trainer_command(name: str, cmd_args: dict) -> tuple[bool, str]:
        if name == "status":
            return True, f"{state['doing']}; queued {jobs.qsize()}; last: {state['last'] or 'none'}"
        if name != "train":
            return False, f"unknown command {name!r}; trainer takes train, status"
        try:
            job = parse_job(state["next"], cmd_args, config)
        except ValueError as exc:
            return False, str(exc)
        state["next"] += 1
        jobs.put(job)
        return True, (f"job {job.number} queued: {job.mode} on {len(job.recordings)} recording(s) "
                      f"({', '.join(os.path.basename(r) for r in job.recordings)})")

    def worker(n: Node) -> None:
        while not n.stopping:
            try:
                job = jobs.get(timeout=0.2)
            except queue.Empty:
                continue
            state["doing"] = f"training job {job.number} ({job.mode})"
            n.event("info", f"job {job.number} started: {job.mode} on {list(job.recordings)}")
            try:
                result = train_job(job, config, n.keys.vehicle, state["active"], offer, state["certificate"])
                state["last"] = f"job {job.number} done: {result.network_id}"
                n.event("info", f"job {job.number} done: {result.summary()}")
            except Exception as exc:  # a bad recording or request must not stop the trainer
                state["last"] = f"job {job.number} failed: {exc}"
                n.event("error", f"job {job.number} failed: {type(exc).__name__}: {exc}")
            state["doing"] = "idle"

    node.subscribe("network", on_network)
    node.on_command(trainer_command)
    node.status_hook = lambda: f"ok, {state['doing']}, queued {jobs.qsize()}"
    return run_node(node, worker)
