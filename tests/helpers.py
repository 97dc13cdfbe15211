"""Builders shared by the tests of every tier: networks, measurements, messages, recordings on disk,
and the figures tests compare against (taken from the code's own config, never copied).

Pure: no bus, no processes, no fixtures with side effects. Running things (free ports, Zenoh
sessions, `neso` subprocesses) is :mod:`tests.busutil`; the browser is :mod:`tests.browser.chromium`.
Test modules import from these three, never from each other.
"""
from __future__ import annotations

import json
import random
import re
import struct
import sys
import threading
from pathlib import Path

import numpy as np

from neso.control import ControlConfig
from neso.netfile import load_network
from neso.network import LipschitzMLP
from neso.rotations import world_from_body_zyx
from neso.types import StateMeasurement
from recordings.writer import FlightWriter
from runtime.schema import (TOPICS, CommandReply, CommandRequest, EstimateMsg, EventMsg, HealthMsg, Message, NetworkMsg,
                            ParamReply, ParamRequest, ParamStateMsg, RecordingMsg, ReferenceMsg, ReplayMsg, SetpointMsg,
                            PreflightMsg, SchemaError, StateMsg, TelemetryMsg, TruthMsg)

REPO = Path(__file__).resolve().parents[1]
BASE = str(REPO / "networks" / "base.safetensors")  # the network the estimator flies by default
EXAMPLE = REPO / "recordings" / "examples" / "nominal-landing-eso.rrd"  # the shipped example flight
PERIOD_S = 0.02  # `neso up`'s default control period (50 Hz)
FORCE_STEP_LIMIT_N = ControlConfig(dt_s=PERIOD_S).force_step_limit_n  # the controller's, per sample at 50 Hz


# -- networks ---------------------------------------------------------------------------------
def random_network(seed: int = 0, sizes=(5, 20, 25, 10, 1), bound: float = 10.0) -> LipschitzMLP:
    rng = np.random.default_rng(seed)
    ws = tuple(rng.normal(0, 0.5, (o, i)) for i, o in zip(sizes[:-1], sizes[1:]))
    bs = tuple(rng.normal(0, 0.1, o) for o in sizes[1:])
    net = LipschitzMLP(ws, bs, np.zeros(sizes[0]), np.ones(sizes[0]), np.zeros(sizes[-1]), np.ones(sizes[-1]), 1e9)
    return net.scaled_to_bound(bound)


def with_meta(net: LipschitzMLP, **meta) -> LipschitzMLP:
    return LipschitzMLP(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                        net.lipschitz_bound, {**net.metadata, **{k: str(v) for k, v in meta.items()}}, net.bound_units)


def candidate(seed=1, vehicle="uav1", scale=1.0, **meta) -> LipschitzMLP:
    """The shipped base network perturbed, within its bound; with ``scale`` > 1 widened until its certified
    slope in the state inputs is ``scale`` times that bound (uncertified for scale ≥ 1.2): a network the
    estimator's gate accepts."""
    base = load_network(BASE)
    rng = np.random.default_rng(seed)
    ws = tuple(w + rng.normal(0, 0.02, w.shape) for w in base.weights)
    net = LipschitzMLP(ws, base.biases, base.input_mean, base.input_std, base.output_mean, base.output_std,
                       1e9, dict(base.metadata), base.bound_units)
    if "blocks" in base.metadata:  # the perturbation must not push its attitude slopes over the base's own bounds
        blocks, bounds = json.loads(base.metadata["blocks"]), json.loads(base.metadata["block_bounds"])
        net = net.within_block_bounds(blocks, [b * min(scale, 1.0) for b in bounds])
    net = widened(net, scale * base.lipschitz_bound) if scale > 1 else net.scaled_to_bound(scale * base.lipschitz_bound)
    return with_meta(net, id=f"cand-{seed}", vehicle=vehicle, val_loss=0.05, **meta)


def widened(net: LipschitzMLP, state_lipschitz: float) -> LipschitzMLP:
    """``net`` with every layer scaled alike (biases by the running factor: the same shape, a steeper slope) so
    its certified slope in the state inputs is ``state_lipschitz``, which it states as its bound (physical)."""
    c = (state_lipschitz / net.certified_lipschitz_state()) ** (1 / net.n_layers)
    ws = tuple(w * c for w in net.weights)
    bs = tuple(b * c ** (i + 1) for i, b in enumerate(net.biases))
    return LipschitzMLP(ws, bs, net.input_mean, net.input_std, net.output_mean, net.output_std, state_lipschitz,
                        dict(net.metadata), "physical")


def with_header(data: bytes, **meta: str) -> bytes:
    """A network file's bytes: the same tensors under a header whose metadata says otherwise (e.g. another
    stated ``lipschitz_bound``, another ``feature_set``)."""
    (hlen,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + hlen])
    header["__metadata__"].update(meta)
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    return struct.pack("<Q", len(raw)) + raw + data[8 + hlen:]


def nan_weights(data: bytes) -> bytes:
    """A network file's bytes with one weight of its second layer set to NaN."""
    (hlen,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + hlen])
    begin = header["layers.1.weight"]["data_offsets"][0] + 8 + hlen
    return data[:begin] + struct.pack("<d", float("nan")) + data[begin + 8:]


# -- measurements and messages ----------------------------------------------------------------
def measurement(pos=(0.0, 0.0, 1.0), vel=(0.0, 0.0, 0.0), t_s=0.0, roll=0.0, pitch=0.0) -> StateMeasurement:
    return StateMeasurement(t_s=t_s, pos_enu_m=np.array(pos, float), vel_enu_mps=np.array(vel, float),
                            roll_rad=roll, pitch_rad=pitch, yaw_rad=0.0)


def estimate(seq, fz=0.5, warm=100) -> EstimateMsg:
    """A warm Neural-ESO estimate for sample ``seq`` with f̂_z = ``fz`` m/s²."""
    return EstimateMsg(seq=seq, stamp_s=1.0, t_s=0.02 * (seq + 1), f_hat_mps2=(0.0, 0.0, fz), f_n_mps2=(0.0, 0.0, fz),
                       delta_f_hat_mps2=(0.0, 0.0, 0.0), z=(1.0, 0.0, 9.81, 0.0, 0.0), pathway="neural_eso",
                       network_id="x", warm_ticks=warm)


def max_force_step_n(setpoints) -> float:
    """Largest change of one component of the commanded force F = T·R e_z between consecutive setpoints
    (the controller limits it to ``ControlConfig.force_step_limit_n``)."""
    forces = [m.thrust_n * world_from_body_zyx(m.roll_rad, m.pitch_rad, m.yaw_rad)[:, 2] for m in setpoints]
    return float(np.max(np.abs(np.diff(forces, axis=0))))


# -- recordings -------------------------------------------------------------------------------
def flight_messages(n: int, *, pathway="eso", on_ground_until=0, thrust_zero_from=None, seq0=0, warm0=0):
    """A synthetic flight: n samples of every sampled topic plus some per-service messages."""
    rng = np.random.default_rng(n)
    out = []
    for k in range(n):
        seq, t, stamp = seq0 + k, (seq0 + k) * PERIOD_S, 100.0 + (seq0 + k) * PERIOD_S
        pos, vel = tuple(rng.normal(size=3)), tuple(rng.normal(size=3))
        out.append(("state", StateMsg(seq=seq, stamp_s=stamp, t_s=t, pos_enu_m=pos, vel_enu_mps=vel, roll_rad=0.01 * k % 1,
                                      pitch_rad=-0.02, yaw_rad=0.3, source="sim")))
        out.append(("truth", TruthMsg(seq=seq, stamp_s=stamp, t_s=t, pos_enu_m=pos, vel_enu_mps=vel,
                                      disturbance_acc_enu_mps2=tuple(rng.normal(size=3)), on_ground=k < on_ground_until,
                                      crashed=False, scenario="nominal_landing")))
        z = tuple(rng.normal(size=5))
        f_n, delta = tuple(rng.normal(size=3)), tuple(rng.normal(size=3))
        out.append(("estimate", EstimateMsg(seq=seq, stamp_s=stamp + 1e-4, t_s=t, f_hat_mps2=tuple(np.add(f_n, delta)),
                                            f_n_mps2=f_n, delta_f_hat_mps2=delta, z=z, pathway=pathway,
                                            network_id="base-L1.0", warm_ticks=warm0 + k + 1)))
        thrust = 0.0 if thrust_zero_from is not None and k >= thrust_zero_from else 6.5
        out.append(("setpoint", SetpointMsg(seq=seq, stamp_s=stamp + 2e-4, state_stamp_s=stamp, t_s=t, roll_rad=0.0,
                                            pitch_rad=0.01, yaw_rad=0.3, thrust_norm=thrust / 20, thrust_n=thrust,
                                            acc_cmd_enu_mps2=(0.0, 0.1, -0.2), estimate_source="estimator")))
        out.append(("reference", ReferenceMsg(seq=seq, stamp_s=stamp + 2e-4, t_s=t, pos_enu_m=pos, vel_enu_mps=vel,
                                              acc_enu_mps2=(0.0, 0.0, 0.0), yaw_rad=0.3, segment="hover")))
        if k % 50 == 0:
            out.append(("health/estimator", HealthMsg(stamp_s=stamp, service="estimator", pid=7, uptime_s=t, ticks=k,
                                                      rate_hz=50.0, latency_p50_ms=0.2, latency_p99_ms=0.5,
                                                      rejected={"state": 0.0}, staleness_s={"state": 0.01}, status="ok")))
    out.insert(3, ("params/estimator", ParamStateMsg(stamp_s=100.0, service="estimator", seq=0,
                                                     values={"pathway": pathway, "lipschitz_bound": 1.0}, note="start")))
    out.insert(4, ("event/controller", EventMsg(stamp_s=100.0, service="controller", level="info", text="took off")))
    return out


def write_recording(path, messages, *, flush_every=100, close=True, vehicle="uav1"):
    w = FlightWriter(path, vehicle=vehicle, flight="uav1-test", segment=0, properties={"params": {"estimator": {"pathway": "eso"}}})
    for i, (channel, msg) in enumerate(messages):
        w.add(channel, msg)
        if i % flush_every == flush_every - 1:
            w.flush()
    if close:
        w.close()
    else:
        w.flush()
    return w


V3 = (0.1, -2.5, 1e-300)
EXAMPLES: list[Message] = [  # one of every message type (tests/unit/test_schema.py checks that it is every one)
    StateMsg(seq=3, stamp_s=12.5, t_s=0.06, pos_enu_m=V3, vel_enu_mps=V3, roll_rad=0.1, pitch_rad=-0.2,
             yaw_rad=3.0, source="sim"),
    TruthMsg(seq=3, stamp_s=1.0, t_s=0.06, pos_enu_m=V3, vel_enu_mps=V3, disturbance_acc_enu_mps2=V3,
             on_ground=False, crashed=False, scenario="nominal_landing"),
    EstimateMsg(seq=3, stamp_s=1.0, t_s=0.06, f_hat_mps2=V3, f_n_mps2=V3, delta_f_hat_mps2=V3,
                z=(1.0, 0.0, 9.81, 0.01, -0.02), pathway="neural_eso", network_id="base-L1", warm_ticks=4),
    SetpointMsg(seq=3, stamp_s=1.0, state_stamp_s=0.9, t_s=0.06, roll_rad=0.0, pitch_rad=0.1, yaw_rad=0.0,
                thrust_norm=0.5, thrust_n=9.81, acc_cmd_enu_mps2=V3, estimate_source="estimator",
                estimate_stamp_s=0.95),
    ReferenceMsg(seq=3, stamp_s=1.0, t_s=0.06, pos_enu_m=V3, vel_enu_mps=V3, acc_enu_mps2=V3, yaw_rad=0.0,
                 segment="landing_test"),
    EventMsg(stamp_s=1.0, service="controller", level="warning", text="flying on the local ESO"),
    HealthMsg(stamp_s=1.0, service="estimator", pid=42, uptime_s=3.0, ticks=150, rate_hz=50.0, latency_p50_ms=0.1,
              latency_p99_ms=0.3, rejected={"state": 2.0}, staleness_s={"state": 0.01}, status="ok",
              counters={"deadline_misses": 3.0}),
    ParamRequest(op="set", values={"pathway": "eso", "lipschitz_bound": 0.5}),
    ParamReply(ok=False, service="estimator", values={"pathway": "eso"}, error="why"),
    ParamStateMsg(stamp_s=1.0, service="estimator", seq=10, values={"pathway": "eso"}, note="pathway eso"),
    CommandRequest(name="takeoff", args={"height_m": 1.0}),
    CommandReply(ok=True, service="controller", message="takeoff starts at the next sample"),
    TelemetryMsg(stamp_s=1.0, connected=True, armed=True, in_air=True, flight_mode="OFFBOARD", roll_rad=0.01,
                 pitch_rad=-0.02, yaw_rad=1.5, pos_enu_m=V3, vel_enu_mps=V3, battery_v=15.8, battery_remaining=0.8,
                 hover_thrust_norm=0.42, setpoint_age_s=0.02, failsafe=""),
    RecordingMsg(stamp_s=1.0, recording=True, flight="uav1-20261121-050000", segment=0,
                 path="recordings/uav1-20261121-050000.rrd", duration_s=12.5, size_bytes=123456, dropped=0),
    NetworkMsg(stamp_s=1.0, seq=100, active={"id": "base-L1", "source": "file", "lipschitz_norm": 1.0,
                                             "lipschitz_phys": 31.6},
               candidate={}, previous={}, shadow_error_rms_mps2=-1.0),
    PreflightMsg(stamp_s=1.0, checked_s=0.9, go=False,
                 items={"EKF2_EV_QMIN": ["no-go", "0", "param set EKF2_EV_QMIN 1"], "battery": ["go", "82 %", ""]}),
    ReplayMsg(stamp_s=1.0, file="out/imports/px4-sitl-takeoff-hover.rrd",
              origin="PX4 log px4-sitl-takeoff-hover.ulg · PX4 v1.15.0 · PX4_SITL", t_s=3.5, duration_s=31.0,
              speed=2.0, playing=True),
]


def velocity_feedback_network(gain: float, *, vehicle: str = "uav1", sizes=(5, 20, 25, 10, 1)) -> LipschitzMLP:
    """A deliberately bad network of the shipped network's shape and inputs (state_speed@1, v_z is input 1):
    f_N = ``gain``·v_z exactly. A negative gain takes damping away from the altitude loop (its Lipschitz
    constant |gain|, certified from the weights as 2·|gain|, is far outside the stability certificate, so it
    flies only by force)."""
    ws = [np.zeros((o, i)) for i, o in zip(sizes[:-1], sizes[1:])]
    ws[0][0, 1], ws[0][1, 1] = 1.0, -1.0  # relu(v_z), relu(−v_z)
    for w in ws[1:-1]:
        w[0, 0] = w[1, 1] = 1.0  # passed on unchanged (both are ≥ 0)
    ws[-1][0, 0], ws[-1][0, 1] = gain, -gain
    bs = [np.zeros(o) for o in sizes[1:]]
    meta = {"id": f"velocity-feedback{gain:g}", "feature_set": "state_speed@1", "val_loss": "0.1", "vehicle": vehicle}
    return LipschitzMLP(tuple(ws), tuple(bs), np.zeros(sizes[0]), np.ones(sizes[0]), np.zeros(1), np.ones(1),
                        2.0 * abs(gain), meta, "physical")


def paper_error_system(kp: float, kd: float, omega_o: float) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (5×5), ``b`` (5,) of ``Ė = AE + bΔḟ``, ``E = [e, ė, x̃1, x̃2, f̃]``, one axis, written out from the
    paper (``ë = −k_p e − k_d ė − f̃``; observer poles at ``−ω_o``), independently of :mod:`neso.certificate`."""
    a = np.zeros((5, 5))
    a[0, 1], a[1, 0], a[1, 1], a[1, 4] = 1.0, -kp, -kd, -1.0
    w = omega_o
    a[2:, 2:] = [[-3 * w, 1.0, 0.0], [-3 * w * w, 0.0, 1.0], [-(w**3), 0.0, 0.0]]
    return a, np.array([0.0, 0.0, 0.0, 0.0, 1.0])


def lemma1_bound(inp, e: np.ndarray) -> np.ndarray:
    """Lemma 1's bound on ``|Δḟ|`` (m/s³) at error states ``e`` (rows of 5), corrected ``λ_c``."""
    lam_c = np.hypot(inp.kp, inp.kd + 1.0)
    return inp.lipschitz * (lam_c * np.linalg.norm(e[:, :2], axis=1) + np.linalg.norm(e[:, 2:], axis=1)) + inp.C_f


def worst_case_run(inp, p: np.ndarray, e0: np.ndarray, *, dt_s: float = 1e-3, steps: int = 8000,
                   every: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """The error system driven by the ``Δḟ`` that raises ``V = EᵀPE`` fastest within Lemma 1 (``|Δḟ|`` at its
    bound, sign of ``∂V̇/∂Δḟ``, + at 0), fixed-step RK4 from the rows of ``e0`` (N×5). Returns ``t_s`` (K,) and
    the states (K×N×5) every ``every`` steps."""
    a, b = paper_error_system(inp.kp, inp.kd, inp.omega_o)

    def rhs(x: np.ndarray) -> np.ndarray:
        s = np.where(x @ p @ b >= 0, 1.0, -1.0)
        return x @ a.T + np.outer(s * lemma1_bound(inp, x), b)

    e = np.array(e0, dtype=float)
    ts, out = [], []
    for k in range(1, steps + 1):
        k1 = rhs(e)
        k2 = rhs(e + 0.5 * dt_s * k1)
        k3 = rhs(e + 0.5 * dt_s * k2)
        e = e + dt_s / 6 * (k1 + 2 * k2 + 2 * k3 + rhs(e + dt_s * k3))
        if k % every == 0:
            ts.append(k * dt_s)
            out.append(e.copy())
    return np.array(ts), np.array(out)


def named_samples(report: str) -> set[int]:
    """The sample numbers a source's deadline report names ("… at samples 280–283, 291 (late in: …)"),
    the inverse of ``flight.deadline.seq_ranges``; none when it names none."""
    if " at sample" not in report:
        return set()
    ranges = report.split(" at sample", 1)[1].split(" (", 1)[0]  # "s 280–283, 291"
    return {k for a, b in re.findall(r"(\d+)(?:–(\d+))?", ranges) for k in range(int(a), int(b or a) + 1)}


def fixed_clock() -> float:
    """The step objects' clock in unit tests (``clock=``): a fixed 0 s, so their outputs are reproducible."""
    return 0.0


def up_args(*argv: str):
    """The parsed command line of ``neso up ARGV…`` (no processes started)."""
    import argparse

    from cli.up import add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    return parser.parse_args(["up", *argv])


def race_the_next_wait(loop, event, update) -> threading.Event:
    """Run ``update()`` on another thread inside the next ``event.wait()`` on asyncio ``loop``, after
    it found the event clear and before it registers its waiter (the window in which a thread-unsafe
    ``set()`` loses the waiter). The returned event is set once it ran."""
    ran = threading.Event()
    original = loop.create_future

    def create_future():
        caller = sys._getframe(1)
        if caller.f_code.co_name == "wait" and caller.f_locals.get("self") is event:
            loop.create_future = original
            other = threading.Thread(target=update)
            other.start()
            other.join()
            ran.set()
        return original()
    loop.create_future = create_future
    return ran


def malformed(valid: bytes, rng: random.Random) -> bytes:
    """A payload that may not be a valid message: random bytes, or ``valid`` broken somehow (cut short, a wrong
    version, a field missing or of a wrong kind)."""
    import msgpack

    body = msgpack.unpackb(valid)
    kind = rng.randrange(6)
    if kind == 0:
        return bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 300)))
    if kind == 1:
        return valid[: rng.randrange(0, len(valid))]
    if kind == 2:
        return msgpack.packb({**body, "v": rng.choice([0, 2, 99, "1", None])})
    name = rng.choice([k for k in body if k not in ("v", "type")])
    if kind == 3:
        del body[name]
        return msgpack.packb(body)
    value = rng.choice([float("nan"), float("inf"), -1, 1e12, "x", None, [1.0], {"a": 1}, True, b"\x00"])
    return msgpack.packb({**body, name: value})


def malformed_payloads(topic: str, valid: bytes, n: int, rng: random.Random) -> list[bytes]:
    """``n`` payloads for ``topic`` built by :func:`malformed` from ``valid`` that its schema really refuses."""
    payloads = []
    while len(payloads) < n:
        p = malformed(valid, rng)
        try:
            TOPICS[topic].from_bytes(p)
        except SchemaError:
            payloads.append(p)  # only ever send what really is invalid
    return payloads
