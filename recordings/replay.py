"""Replaying a recorded flight: in the Rerun viewer, back onto the bus, or through another estimator.

- :func:`viewer_argv`: the ``rerun`` command that opens a file (native, or the web viewer served
  on loopback at explicit ports: if a port is taken, rerun would stream into whatever is there).
- :func:`bus_schedule` + :func:`publish_schedule`: the recorded samples in flight order, published
  again at the flight's pace (× ``speed``) under a vehicle name, stamped with the replay's
  clock, states marked ``source="replay"``.
- :func:`what_if`: another estimator configuration (pathway, L_N, ω_o, network) run offline
  on the recorded states and setpoints through the estimator service's own step object, and
  its f̂ compared with the one that flew (and with the simulator's disturbance if recorded).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neso.types import OMEGA_O_RPS
from recordings.offline import run_estimator, sample_period_s
from recordings.reader import Recording, RecordingError, read_recording, rerun_cli
from runtime.graph import OUTSIDERS
from runtime.schema import Keys, Message, ReplayMsg, StateMsg

REPLAYED = next(o for o in OUTSIDERS if o.name == "replay").publishes  # what its certificate may put


def viewer_argv(path: str | Path, *, web: bool = False, web_port: int = 9090, grpc_port: int = 9876) -> list[str]:
    """``rerun`` opening ``path``: native viewer, or web viewer on 127.0.0.1 at the given ports."""
    if not Path(path).is_file():
        raise RecordingError(f"{path}: no such file")
    argv = [rerun_cli(), str(path)]
    if web:
        argv += ["--web-viewer", "--bind", "127.0.0.1", "--web-viewer-port", str(web_port), "--port", str(grpc_port)]
    return argv


# -- back onto the bus ------------------------------------------------------------------------
def bus_schedule(rec: Recording, topics=REPLAYED) -> list[tuple[float, str, Message]]:
    """(seconds of flight time after the first sample, topic, message), in the order the samples
    were flown and, within a sample, published. Paced by the sample time ``t_s`` (not the wall
    clock), so a lockstep recording replays at the pace of real flight."""
    items = []
    for topic in topics:
        for msg in rec.channel(topic).messages():
            items.append((msg.t_s, msg.seq, msg.stamp_s, topic, msg))
    if not items:
        raise RecordingError(f"{rec.path}: nothing to replay (no {', '.join(topics)} messages)")
    items.sort(key=lambda x: x[:3])
    t0 = items[0][0]
    return [(t - t0, topic, msg) for t, _, _, topic, msg in items]


def restamped(msg: Message, now_s: float) -> Message:
    """``msg`` stamped with the replay's clock (states marked as replayed)."""
    changes = {"stamp_s": now_s}
    if isinstance(msg, StateMsg):
        changes["source"] = "replay"
    if hasattr(msg, "state_stamp_s"):
        changes["state_stamp_s"] = now_s
    return dataclasses.replace(msg, **changes)


def origin_of(rec: Recording) -> str:
    """What a recording records, in a line: a PX4 log or NanoBench flight imported (file, version, hardware) or a
    flight of this system."""
    imported = rec.properties.get("import")
    if isinstance(imported, dict) and imported.get("format") == "NanoBench CSV":
        return (f"NanoBench flight {imported.get('file_name', '?')} · {imported.get('hardware', '?')} firmware "
                f"{imported.get('firmware', '?')} · Vicon")
    if isinstance(imported, dict):
        return (f"PX4 log {imported.get('file_name', '?')} · PX4 {str(imported.get('px4_version', '?')).split(' ')[0]} · "
                f"{imported.get('hardware', '?')}" + (" · mass assumed" if imported.get("mass_assumed") else ""))
    flight = rec.properties.get("flight", {})
    sources = "/".join(dict.fromkeys(rec.channel("state").columns.get("source", []))) or "?"
    return f"flight {flight.get('flight', Path(rec.path).stem)} of {flight.get('vehicle', '?')} ({sources})"


def publish_schedule(session, vehicle: str, schedule, *, speed: float = 1.0, stop=None, on_progress=None,
                     wait_for_subscribers_s: float = 2.0, provenance: tuple[str, str] | None = None) -> int:
    """Publish ``schedule`` under ``neso/<vehicle>/`` at the recorded pace × ``speed``; the count
    published. Waits up to ``wait_for_subscribers_s`` for someone to listen (a session that has just
    opened does not know its subscribers yet, and the first samples would go nowhere).
    ``provenance`` (file, origin): announced on ``neso/<vehicle>/replay`` at the start, once a second
    and at the end, so watchers label the samples as a replay (not counted in the result)."""
    if not speed > 0:
        raise ValueError(f"speed must be positive, got {speed}")
    keys = Keys(vehicle)
    import zenoh

    # BLOCK: a replay is a recording's data, not a live loop's latest sample: never drop one
    pubs = {topic: session.declare_publisher(keys.topic(topic), express=True,
                                             congestion_control=zenoh.CongestionControl.BLOCK)
            for topic in {t for _, t, _ in schedule}}
    deadline = time.monotonic() + wait_for_subscribers_s
    while time.monotonic() < deadline and not any(p.matching_status.matching for p in pubs.values()):
        time.sleep(0.02)
    time.sleep(0.1 if time.monotonic() < deadline else 0.0)  # the other topics' routes come up together
    announce = session.declare_publisher(keys.topic("replay")) if provenance is not None else None
    duration_s = schedule[-1][0] if schedule else 0.0

    def say(t_s: float, playing: bool) -> None:
        if announce is not None:
            announce.put(ReplayMsg(stamp_s=time.monotonic(), file=provenance[0][:1024], origin=provenance[1][:1024],
                                   t_s=max(0.0, t_s), duration_s=duration_s, speed=speed, playing=playing).to_bytes())

    start = time.monotonic()
    n, offset_s, next_say = 0, 0.0, start
    try:
        for offset_s, topic, msg in schedule:
            if stop is not None and stop.is_set():
                break
            delay = start + offset_s / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if time.monotonic() >= next_say:
                say(offset_s, True)
                next_say += 1.0
            pubs[topic].put(restamped(msg, time.monotonic()).to_bytes())
            n += 1
            if on_progress is not None and topic == "state" and msg.seq % 250 == 0:
                on_progress(offset_s, msg)
    finally:
        say(offset_s, False)
        for pub in pubs.values():
            pub.undeclare()
        if announce is not None:
            announce.undeclare()
    return n


# -- what if another estimator had flown ------------------------------------------------------
@dataclass(frozen=True)
class WhatIf:
    """``pathway``/``lipschitz_bound``/``omega_o_rps``/``network`` (None: as recorded / default)."""

    pathway: str | None = None
    lipschitz_bound: float | None = None
    omega_o_rps: float | None = None
    network: str | None = None

    @classmethod
    def parse(cls, text: str) -> "WhatIf":
        """``pathway=eso,lipschitz_bound=0.5,omega_o=20,network=networks/x.safetensors``; a
        ``ValueError`` naming the setting that is wrong (before anything is computed)."""
        from runtime.schema import PATHWAYS

        names = {"pathway": "pathway", "lipschitz_bound": "lipschitz_bound", "L_N": "lipschitz_bound",
                 "omega_o": "omega_o_rps", "omega_o_rps": "omega_o_rps", "network": "network"}
        values: dict = {}
        for part in text.replace(" ", ",").split(","):
            if not part:
                continue
            if "=" not in part:
                raise ValueError(f"{part!r}: expected name=value (names: {sorted(names)})")
            k, v = part.split("=", 1)
            if k not in names:
                raise ValueError(f"unknown what-if setting {k!r}; known: {sorted(names)}")
            if names[k] in ("lipschitz_bound", "omega_o_rps"):
                try:
                    number = float(v)
                except ValueError:
                    raise ValueError(f"{k}={v}: not a number") from None
                if not (math.isfinite(number) and number > 0):
                    raise ValueError(f"{k}={v}: must be a positive number")
                values[names[k]] = number
            elif names[k] == "pathway" and v not in PATHWAYS:
                raise ValueError(f"pathway={v}: not one of {', '.join(PATHWAYS)}")
            elif names[k] == "network" and not Path(v).is_file():
                raise ValueError(f"network={v}: no such file")
            else:
                values[names[k]] = v
        return cls(**values)


@dataclass(frozen=True)
class Comparison:
    config: dict
    samples: int
    diff_rms_mps2: tuple[float, float, float]  # what-if f̂ − flown f̂, per axis
    diff_max_mps2: tuple[float, float, float]
    flown_err_rms_mps2: tuple[float, float, float] | None  # against the simulator's disturbance
    whatif_err_rms_mps2: tuple[float, float, float] | None
    f_hat_whatif_mps2: np.ndarray  # (N, 3)
    f_hat_flown_mps2: np.ndarray  # (N, 3)
    seq: np.ndarray  # (N,)
    against: str = "flown"  # what the what-if is compared with: the f̂ flown, or the ESO run offline (none flew)

    def report(self) -> str:
        fmt = lambda v: "(" + ", ".join(f"{x:.4f}" for x in v) + ")"  # noqa: E731
        lines = [f"what-if {self.config} over {self.samples} samples (x, y, z in m/s²):",
                 f"  f̂ what-if − f̂ {self.against}: RMS {fmt(self.diff_rms_mps2)}, max |·| {fmt(self.diff_max_mps2)}"]
        if self.flown_err_rms_mps2 is not None:
            lines += [f"  against the simulator's disturbance: {self.against} RMS {fmt(self.flown_err_rms_mps2)}, "
                      f"what-if RMS {fmt(self.whatif_err_rms_mps2)}"]
        return "\n".join(lines)


def what_if(rec: Recording, change: WhatIf, *, skip_s: float = 0.5) -> Comparison:
    """Run the estimator service's step object with ``change`` on the recorded states and setpoints
    (in their recorded arrival order, :func:`recordings.offline.run_estimator`) and compare its f̂
    with the recorded one."""
    from flight.estimator import DEFAULT_NETWORK, EstimatorConfig, EstimatorCore, NetworkChoice, load_flown_network

    states, setpoints = rec.channel("state").messages(), rec.channel("setpoint").messages()
    estimates = rec.channel("estimate").messages()
    flown = {m.seq: m.f_hat_mps2 for m in estimates}
    against, flown_pathway = "flown", estimates[0].pathway if estimates else "eso"
    if states and setpoints and not flown:  # none of ours flew (an imported PX4 log): the ESO teacher is the reference
        from recordings.teacher import eso_teacher

        run = eso_teacher(rec, skip_s=skip_s)
        flown = {int(s): tuple(f) for s, f, warm in zip(run.seq, run.f_hat_mps2, run.warm) if warm}
        against = "ESO offline"
    if not states or not flown:
        raise RecordingError(f"{rec.path}: needs recorded states and estimates (or setpoints for the offline ESO)")
    recorded = rec.properties.get("params", {}).get("estimator", {})
    recorded = recorded if isinstance(recorded, dict) else {}
    dt = sample_period_s([m.t_s for m in states])
    pathway = change.pathway or recorded.get("pathway") or flown_pathway
    config = EstimatorConfig(network=change.network if change.network is not None else DEFAULT_NETWORK,
                             pathway=pathway, omega_o_rps=change.omega_o_rps or OMEGA_O_RPS, dt_s=dt)
    network, source = load_flown_network(config.network)
    choice = NetworkChoice(network, source, config.network_dir)
    loaded_id = network.metadata.get("id", "unnamed") if network is not None else "none"
    bound = change.lipschitz_bound
    if bound is None and network is not None and {m.network_id for m in estimates} == {loaded_id}:
        bound = recorded.get("lipschitz_bound")  # the recorded L_N, when the recording flew this network
    if bound is not None and network is not None and not np.isclose(bound, network.lipschitz_bound_physical()):
        refusal = choice.refusal(float(bound))
        if refusal:
            raise ValueError(refusal)

    cores: list[EstimatorCore] = []  # one per recorded segment; the last one names the network that ran

    def make_core(dt_s: float) -> EstimatorCore:
        core = EstimatorCore(dataclasses.replace(config, dt_s=dt_s), network, choice, clock=time.monotonic)
        if bound is not None and network is not None and not np.isclose(bound, network.lipschitz_bound_physical()):
            core.apply({"lipschitz_bound": float(bound)})
        cores.append(core)
        return core

    ours = run_estimator(states, setpoints, make_core)
    common = sorted(s for s in set(ours) & set(flown) if ours[s].warm_ticks * dt >= skip_s)
    if not common:
        raise RecordingError(f"{rec.path}: no sample where both estimates are warm")
    a = np.array([ours[s].f_hat_mps2 for s in common])
    b = np.array([flown[s] for s in common])
    d = a - b
    truth = {m.seq: m for m in rec.channel("truth").messages()}
    flown_err = whatif_err = None
    if truth and all(s in truth for s in common):
        dist = np.array([truth[s].disturbance_acc_enu_mps2 for s in common])
        flown_err = tuple(np.sqrt(np.mean((b - dist) ** 2, axis=0)))
        whatif_err = tuple(np.sqrt(np.mean((a - dist) ** 2, axis=0)))
    core = cores[-1]
    info = core.active_info  # the network that ran: the file asked for, one trained for L_N, or one scaled to it
    ran = f"{core.network_id} ({info.get('source')} {info.get('path')})" if network is not None else "none"
    if pathway == "eso":
        ran += ", unused: the eso pathway flies no network"
    used = {"pathway": pathway, "lipschitz_bound": bound, "omega_o_rps": config.omega_o_rps, "network": ran}
    return Comparison(config=used, samples=len(common), diff_rms_mps2=tuple(np.sqrt(np.mean(d**2, axis=0))),
                      diff_max_mps2=tuple(np.max(np.abs(d), axis=0)), flown_err_rms_mps2=flown_err,
                      whatif_err_rms_mps2=whatif_err, f_hat_whatif_mps2=a, f_hat_flown_mps2=b, seq=np.array(common),
                      against=against)


def load(path: str | Path) -> Recording:
    return read_recording(path)
