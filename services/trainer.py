"""``trainer``: trains a network on recorded flights, certifies it, stores it, offers it to the estimator.

One per vehicle. Training runs in a worker thread of this process (never in the control loop's
processes; torch is imported here only), one job at a time, so the node keeps answering health
and commands while it trains. Commands on ``neso/<v>/cmd/trainer``:

- ``train {recordings?, label?, lipschitz_bound?, epochs?, offer?, seed?}``: queue a job; the
  reply says the job number at once. ``recordings``: ``.rrd`` paths (default: the newest one in
  ``--recordings-dir``, which may be the flight still being recorded: it is read up to its last
  flush); ``label``: ``tdr`` (default; labels f_N + Δf̂, warm-started from the
  network the estimator flies, keeping its normalisation and so its physical bound) or ``eso``
  (labels x̂_3 flown under the ``eso`` pathway, trained from scratch); ``lipschitz_bound``: L_N
  normalised (default: the active network's for ``tdr``, 1.0 for ``eso``); ``epochs`` (100);
  ``offer`` (true: send the result to the estimator's gate); ``seed`` (0).
- ``status``: what the worker is doing and the last result.

A retried ``train`` is queued once (the node answers a repeated request id with the first answer).

Each job ends with an event ``job <n> done: …`` (network id, registry path, val loss, bounds,
small-gain verdict, stage times, the estimator's answer to the offer) or ``job <n> failed: …``.
What the active network is comes from the estimator's ``NetworkMsg``.
"""
from __future__ import annotations

import argparse
import glob
import os
import queue
import threading
import time
from dataclasses import dataclass, field

from neso.control import ControlConfig
from runtime.schema import NetworkMsg

LABELS = ("tdr", "eso")


@dataclass(frozen=True)
class TrainerConfig:
    registry: str = "networks/registry"
    recordings_dir: str = "out/recordings"
    kp: float = ControlConfig().kp[2]
    kd: float = ControlConfig().kd[2]
    omega_o_rps: float = 15.0
    epochs: int = 100


@dataclass(frozen=True)
class Job:
    """One training request, validated."""

    number: int
    recordings: tuple[str, ...]
    label: str
    lipschitz_bound: float | None
    epochs: int
    offer: bool
    seed: int


@dataclass
class JobResult:
    """What a finished job made. ``timings_s``: stage → seconds; ``offer``: (accepted, estimator's message)."""

    job: Job
    network_id: str = ""
    path: str = ""
    info: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    offer: tuple[bool, str] | None = None

    def summary(self) -> str:
        i = self.info
        cert = i.get("certificate", {})
        times = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings_s.items())
        offer = "" if self.offer is None else (f"; offer {'accepted' if self.offer[0] else 'REFUSED'}: "
                                               f"{self.offer[1]}")
        return (f"{self.network_id} at {self.path}: {i.get('n_samples')} samples from {len(self.job.recordings)} "
                f"recording(s), val_loss {i.get('val_loss'):.4g}, L_N {i.get('lipschitz_norm'):g} normalised = "
                f"{i.get('lipschitz_phys'):.4g} physical (certified {i.get('certified_phys'):.4g}), small-gain "
                f"{'holds' if cert.get('holds') else 'does not hold'} (max certified {cert.get('max_certified_lipschitz')})"
                f"; {times}{offer}")


def parse_job(number: int, args: dict, config: TrainerConfig) -> Job:
    """A :class:`Job` from command args; ``ValueError`` naming what is wrong."""
    unknown = set(args) - {"recordings", "label", "lipschitz_bound", "epochs", "offer", "seed"}
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
    label = args.get("label", "tdr")
    if label not in LABELS:
        raise ValueError(f"label must be one of {LABELS}, got {label!r}")
    bound = args.get("lipschitz_bound")
    if bound is not None and not (isinstance(bound, (int, float)) and not isinstance(bound, bool) and 0 < bound < 1e3):
        raise ValueError(f"lipschitz_bound must be a number in (0, 1000), got {bound!r}")
    epochs = args.get("epochs", config.epochs)
    if not (isinstance(epochs, int) and not isinstance(epochs, bool) and 1 <= epochs <= 10_000):
        raise ValueError(f"epochs must be an integer in [1, 10000], got {epochs!r}")
    offer = args.get("offer", True)
    if not isinstance(offer, bool):
        raise ValueError("offer must be true or false")
    seed = args.get("seed", 0)
    if not (isinstance(seed, int) and not isinstance(seed, bool)):
        raise ValueError("seed must be an integer")
    return Job(number, tuple(os.path.abspath(r) for r in recordings), label,
               None if bound is None else float(bound), epochs, offer, seed)


def active_network(active: dict):
    """The network the estimator flies, from ``NetworkMsg.active`` (its file, scaled to its L_N)."""
    from neso.features import N_FEATURES
    from neso.netfile import load_network

    path = active.get("path", "")
    if not path or not os.path.isfile(path):
        raise ValueError(f"the active network {active.get('id')!r} has no file to warm-start from ({path!r})")
    net = load_network(path, expected_inputs=N_FEATURES, expected_outputs=1)
    bound = float(active.get("lipschitz_norm", net.lipschitz_bound))
    return net.scaled_to_bound(bound) if bound < net.lipschitz_bound else net


def train_job(job: Job, config: TrainerConfig, vehicle: str, active: dict | None, offer_fn=None) -> JobResult:
    """Dataset → training → certificate → registry → offer (``offer_fn(path) -> (ok, message)``)."""
    from neso.training import train_lipschitz_mlp
    from recordings.dataset import load_training_set
    from services import registry

    result = JobResult(job)
    t0 = time.perf_counter()
    ts = load_training_set(list(job.recordings), job.label)
    if ts.vehicle and ts.vehicle != vehicle:
        raise ValueError(f"the recordings are of vehicle {ts.vehicle!r}, this trainer serves {vehicle!r}")
    t1 = time.perf_counter()
    result.timings_s["dataset"] = t1 - t0
    init = None
    parent = ""
    if job.label == "tdr":
        if not active:
            raise ValueError("tdr starts from the active network, and no NetworkMsg came from the estimator yet")
        init = active_network(active)
        parent = str(active.get("id", ""))
    bound = job.lipschitz_bound or (init.lipschitz_bound if init is not None else 1.0)
    res = train_lipschitz_mlp(ts.z, ts.y_mps2, lipschitz_bound=bound, epochs=job.epochs, seed=job.seed, init=init,
                              metadata={"vehicle": vehicle, "parent": parent})
    t2 = time.perf_counter()
    result.timings_s["train"] = t2 - t1
    cert = registry.small_gain_certificate(res.network.certified_lipschitz_physical(), kp=config.kp, kd=config.kd,
                                           omega_o=config.omega_o_rps)
    t3 = time.perf_counter()
    result.timings_s["certify"] = t3 - t2
    entry = registry.store(res.network, root=config.registry, vehicle=vehicle, label=job.label, parent=parent,
                           recordings=list(job.recordings), certificate=cert)
    result.network_id, result.path = entry.id, os.path.abspath(entry.path)
    result.info = dict(entry.info, n_samples=len(ts.y_mps2))
    t4 = time.perf_counter()
    result.timings_s["store"] = t4 - t3
    if job.offer and offer_fn is not None:
        result.offer = offer_fn(result.path)
        result.timings_s["offer"] = time.perf_counter() - t4
    return result


# -- bus adapter ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = TrainerConfig()
    parser.add_argument("--registry", default=d.registry, help="network registry root (default %(default)s)")
    parser.add_argument("--recordings-dir", default=d.recordings_dir, help="where recordings are looked for")
    parser.add_argument("--kp", type=float, default=d.kp, help="controller z gain k_p for the certificate, 1/s²")
    parser.add_argument("--kd", type=float, default=d.kd, help="controller z gain k_d for the certificate, 1/s")
    parser.add_argument("--omega-o", type=float, default=d.omega_o_rps, help="observer bandwidth for the certificate")


def run(args, bus) -> int:
    from runtime.client import ServiceUnavailable, command
    from runtime.node import Node, run_node

    os.nice(10)  # training shares the machine with the control loop: it yields the CPU to it
    config = TrainerConfig(registry=args.registry, recordings_dir=args.recordings_dir, kp=args.kp, kd=args.kd,
                           omega_o_rps=args.omega_o)
    node = Node("trainer", vehicle=args.vehicle, bus=bus, config=config)
    jobs: queue.Queue[Job] = queue.Queue()
    state = {"active": None, "doing": "idle", "last": "", "next": 1}

    def on_network(msg: NetworkMsg, _received_s: float) -> None:
        state["active"] = dict(msg.active)

    def offer(path: str) -> tuple[bool, str]:
        try:
            reply = command(node.session, node.keys, "estimator", "offer", {"path": path}, timeout_s=5.0)
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
        return True, (f"job {job.number} queued: {job.label} on {len(job.recordings)} recording(s) "
                      f"({', '.join(os.path.basename(r) for r in job.recordings)})")

    def worker(n: Node) -> None:
        while not n.stopping:
            try:
                job = jobs.get(timeout=0.2)
            except queue.Empty:
                continue
            state["doing"] = f"training job {job.number} ({job.label})"
            n.event("info", f"job {job.number} started: {job.label} on {list(job.recordings)}")
            try:
                result = train_job(job, config, n.keys.vehicle, state["active"], offer)
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
