"""``neso demo tdr``: the whole Total Disturbance Retraining loop in simulation, on the bus, in real time.

1. ``neso up`` the near-ground lemniscate scenario under Neural-ESO with the base (nominal-trained)
   network, the recorder and the trainer on;
2. fly the lemniscate mission (3 s ramp + 5 cycles of 6 s: 30 s of out-of-distribution data); the
   recorder writes the flight;
3. stop the recording, have the trainer train a TDR network from that ``.rrd`` starting from the
   active network (with its recipe: inputs, label, normalisation, the certified bound), certify it,
   fly the recorded flight again with it and with the active network (the predicted change), store it
   and offer it to the estimator (gate → shadow) if it is predicted to improve;
4. promote it in flight (hovering at the lemniscate's end point), then fly the lemniscate again while
   the estimator's canary compares the tracking with the first run;
5. fly the lemniscate once more with PD+ESO (the estimator's ``eso`` pathway) at the same gains, paired with
   the others; and, in-process (:func:`tuned_pdeso`), PD+ESO in the same scenario and seed at the paper's and at
   the lemniscate's tuned gains (:data:`sim.tuning.TUNED_GAINS`): the baseline a learned pathway is said to pay
   against (issue 32).

The live loop flies the paper's gains (k_p 10, k_d 6, ω_o 15): the shipped networks are certified there, not at
the tuned k_p 40, k_d 12, ω_o 2.5 (the base network's |e_z| bound is ×2.04 PD+ESO's there, over the ×2 allowed),
and the observer bandwidth is a start-up setting that the estimator certifies at the default gains, where ω_o 2.5
gives PD+ESO a 76 cm bound. So the tuned baseline is flown in-process beside it, in the same world.

The two lemniscates are paired: before each, the simulated world restarts (the source's ``scenario``
command: same scenario, same seed, so the same gust and mocap-noise streams) and the lemniscate is
commanded once the world's clock reaches ``PAIRED_START_T_S``. Without that, the second run met a
minute-later stretch of the same turbulence, and the same network's two runs differed by −10 % to
+24 % (docs/tdr.md, "The live loop"); paired, the difference is the network's. When the candidate is
not offered, the second run flies the same network again: the pairing's own residual.

With ``--lockstep-pace P`` the built-in world flies in lockstep, at most P× real time: every state is answered with a
setpoint, so deadlines are not measured (a miss there is the controller's local ESO flying a sample the estimator
left unanswered for ``ControllerConfig.lockstep_stale_s`` of the wall clock; the PX4 loop, in real time, is where
deadlines are), the restarts and the paired starts are the same in the world's time, and the loop takes a fraction of
the wall clock. With ``--world px4`` real PX4 SITL flies the world (``neso up --vehicle px4``): the loop first takes
off as an operator does, and since PX4 would not follow a restarted world the two lemniscates are not paired (one
world flies on; the report says so).

Reported: the z RMSE of the cycles before and after the swap (truth − reference, the ramps left
out), missed deadlines (states without a setpoint from the estimator's f̂), the commanded-force
step at the swap beside the normal steps, the f̂ step at the swap, and the stage times from the
end of the recording to the promoted network. The same function backs the process test
(``tests/process/test_tdr_loop.py``) and the bench row (``bench/tdr.py``).
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from flight.controller import ControllerConfig
from neso.control import ControlConfig
from neso.trajectories import Lemniscate

LOCKSTEP_STALE_S = ControllerConfig().lockstep_stale_s  # the controller's wait before a lockstep miss

RAMP_S = Lemniscate().ramp_s  # the cycles start after it
SCENARIO = "lemniscate_near_ground"
PAIRED_START_T_S = 3.0  # world clock (s) at which each paired lemniscate is commanded
# world clock (s) from which the command is sent: in real time 2 s ahead, so that its latency up to 2 s of the wall
# clock cannot move the start; in lockstep from 0.2 s (a state at 0.2 s means the controller began this world's
# flight: it answered every sample before), 2.8 s of the world ahead, 0.56 s of the wall clock at 5× real time
COMMAND_FROM_T_S = {"real time": PAIRED_START_T_S - 2.0, "lockstep": 0.2}
FORCE_STEP_LIMIT_N = ControlConfig().force_step_limit_n  # the controller's, at neso up's default 50 Hz


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("demo", help="demo missions (tdr: record, retrain, hot-swap in flight)")
    sub = p.add_subparsers(dest="demo", required=True)
    t = sub.add_parser("tdr", help="fly the lemniscate, retrain from the recording, promote in flight, fly again")
    t.add_argument("--hub", default=None, help="hub endpoint (default: a free loopback port)")
    t.add_argument("--workdir", default=None, help="recordings and registry go here (default: a temp dir)")
    t.add_argument("--epochs", type=int, default=100)
    t.add_argument("--dashboard-port", type=int, default=8080, help="watch it at http://127.0.0.1:PORT (0: no dashboard)")
    t.add_argument("--json", default=None, help="write the report here as JSON")
    t.add_argument("--seed", type=int, default=1, help="the simulated world's seed (gusts, mocap noise)")
    t.add_argument("--force-offer", action="store_true",
                   help="offer and promote the candidate even if predicted to fly worse or it learned nothing (to see what "
                        "it does; the certificate still gates it)")
    t.add_argument("--world", default="builtin", choices=("builtin", "px4"),
                   help="builtin: the world's own inner loop, the two lemniscates paired (the world restarts with "
                        "its seed); px4: real PX4 SITL flies the world (`neso up --vehicle px4`), taken off as an "
                        "operator does; its world cannot restart under PX4, so the lemniscates are not paired")
    t.add_argument("--lockstep-pace", type=float, default=0.0,
                   help="the built-in world in lockstep, at most this multiple of real time (0: real time); every "
                        "sample answered, so no deadline is measured")
    t.add_argument("--lemniscate-cycles", type=int, default=None,
                   help="6 s cycles per lemniscate (default: the mission's, 5); fewer make a shorter demo")


@dataclass
class TdrReport:
    """Figures of one TDR loop (see the module docstring); RMSE in cm, forces in N, times in s."""

    rmse_before_cm: float = float("nan")
    rmse_after_cm: float = float("nan")
    improvement: float = float("nan")  # 1 − after/before
    cycles_before_samples: int = 0
    cycles_after_samples: int = 0
    states: int = 0
    missed_setpoints: int = 0  # states in the window with no setpoint, or one made without the estimator
    missed_near_swap: int = 0  # of those, within ±25 samples (0.5 s) of the swap
    states_without_setpoint: int = 0  # of those, no setpoint at all (the rest: the controller's local ESO flew)
    swap_answered: bool = False  # the swap sample and the one after it got setpoints made with the estimator's f̂
    missed_by_phase: dict = field(default_factory=dict)  # first lemniscate / training and swap / second lemniscate
    swap_seq: int = -1
    force_step_at_swap_n: float = float("nan")  # largest commanded-force component step, ±5 samples of the swap
    force_step_p50_n: float = float("nan")
    force_step_p99_n: float = float("nan")
    # f̂_z's steps: the largest over the swap sample and the 5 after it (the new network in the observer), the
    # largest and the 99th percentile elsewhere; the prior's own jump at the swap, which the observer absorbs
    f_hat_step_at_swap_mps2: float = float("nan")
    f_hat_step_max_mps2: float = float("nan")
    f_hat_step_p99_mps2: float = float("nan")
    f_n_jump_at_swap_mps2: float = float("nan")
    shadow_error_rms_mps2: float = float("nan")  # candidate's f_N − f̂ (z) in shadow, just before the promote
    active_error_rms_mps2: float = float("nan")  # the active network's, same samples
    recording: str = ""
    network_id: str = ""
    trainer_summary: str = ""
    stage_s: dict = field(default_factory=dict)
    offered: bool = False  # the trainer offered the candidate (predicted to improve)
    predicted: dict = field(default_factory=dict)  # the trainer's closed-loop prediction (RMSE cm, change)
    certificate: dict = field(default_factory=dict)  # the candidate's, for the gains flown
    canary: str = ""  # the canary's last word after the second run
    lemniscate_start_t_s: list = field(default_factory=list)  # world clock at each run's first lemniscate sample
    world: str = "builtin"  # or "px4": PX4 SITL in the loop, the lemniscates not paired
    lockstep_pace: float = 0.0  # > 0: the built-in world flew in lockstep at most this multiple of real time
    lemniscate_cycles: int = 0  # the 6 s cycles each lemniscate flew
    gains: dict = field(default_factory=dict)  # the z gains flown: kp (1/s²), kd (1/s), omega_o (rad/s)
    rmse_pdeso_cm: float = float("nan")  # PD+ESO at the same gains, the lemniscate's cycles (paired in builtin)
    pdeso_samples: int = 0
    tuned_pdeso: dict = field(default_factory=dict)  # tuned_pdeso(): in-process PD+ESO at the paper's and tuned gains

    def lines(self) -> list[str]:
        from sim.counterfactual import prediction_text

        st = ", ".join(f"{k} {v:.2f}" for k, v in self.stage_s.items())
        g = self.gains
        against = lambda v: f"{(v / self.rmse_pdeso_cm - 1) * 100:+.0f} %" if self.rmse_pdeso_cm > 0 else "–"  # noqa: E731
        return [
            f"z gains flown: k_p {g.get('kp', float('nan')):g}, k_d {g.get('kd', float('nan')):g}, ω_o "
            f"{g.get('omega_o', float('nan')):g}",
            f"z RMSE, lemniscate cycles before the swap (base network): {self.rmse_before_cm:.2f} cm "
            f"({self.cycles_before_samples} samples)",
            f"z RMSE, lemniscate cycles after the swap ({self.network_id}): {self.rmse_after_cm:.2f} cm " if self.offered
            else f"z RMSE, the lemniscate again (base network: {self.network_id} not offered): {self.rmse_after_cm:.2f} cm "
            f"({self.cycles_after_samples} samples) -> change {-100 * self.improvement:+.0f} %",
            f"lockstep at most {self.lockstep_pace:g}× real time, no deadline measured: {self.states} states, "
            f"{self.states_without_setpoint} without a setpoint, {self.missed_setpoints} flown on the controller's "
            f"local ESO (the estimator silent for {LOCKSTEP_STALE_S:g} s of the wall clock; by phase "
            f"{self.missed_by_phase})"
            if self.lockstep_pace > 0 else
            f"missed deadlines: {self.missed_setpoints} of {self.states} states ({self.states_without_setpoint} without "
            f"any setpoint, the rest flown on the controller's local ESO; {self.missed_near_swap} within 0.5 s of the "
            f"swap, swap sample answered: {self.swap_answered}; by phase {self.missed_by_phase})",
            f"commanded force step at the swap {self.force_step_at_swap_n:.3f} N (normal p50 {self.force_step_p50_n:.3f}, "
            f"p99 {self.force_step_p99_n:.3f}, limit {FORCE_STEP_LIMIT_N:.3f}); f̂ step at the swap and the 5 samples "
            f"after {self.f_hat_step_at_swap_mps2:.4f} m/s² (elsewhere p99 {self.f_hat_step_p99_mps2:.4f}, largest "
            f"{self.f_hat_step_max_mps2:.4f}; f_N's own jump at the swap {self.f_n_jump_at_swap_mps2:.4f}, absorbed "
            "by the observer)",
            f"in shadow before the promote: candidate's RMS error against f̂ {self.shadow_error_rms_mps2:.3f} m/s², "
            f"active network's {self.active_error_rms_mps2:.3f} m/s²",
            f"recording -> promoted network, s: {st}",
            f"predicted before the offer (the recorded flight flown again): {prediction_text(self.predicted)}; "
            f"offered: {self.offered}; {self.certificate.get('text', 'certificate unknown')}",
            f"PD+ESO at the same gains, the lemniscate again: {self.rmse_pdeso_cm:.2f} cm ({self.pdeso_samples} samples);"
            f" against it the first run {against(self.rmse_before_cm)}, the second {against(self.rmse_after_cm)}",
            tuned_pdeso_text(self.tuned_pdeso),
            f"canary: {self.canary or 'no verdict'}",
            ("paired worlds (same seed): lemniscates began at world t = " if self.world == "builtin" else
             "PX4 SITL in the loop, not paired (one world flies on: the runs also meet different gusts): lemniscates "
             "began at world t = ") + ", ".join(f"{t:.2f}" for t in self.lemniscate_start_t_s) + " s",
        ]


def _force(sp) -> np.ndarray:
    from neso.rotations import world_from_body_zyx

    return sp.thrust_n * world_from_body_zyx(sp.roll_rad, sp.pitch_rad, sp.yaw_rad)[:, 2]


def lemniscate_runs(references) -> list[tuple[int, int]]:
    """(first seq, last seq) of each run of the ``lemniscate`` segment, in order: a run ends at
    the first reference of another segment (samples whose reference was not seen do not end it)."""
    runs, start, last = [], None, None
    for m in sorted(references, key=lambda m: m.seq):
        if m.segment == "lemniscate":
            start = m.seq if start is None else start
            last = m.seq
        elif start is not None:
            runs.append((start, last))
            start = None
    if start is not None:
        runs.append((start, last))
    return runs


@dataclass(frozen=True)
class Run:
    """One lemniscate flown in its own world: the world's first state stamp and the next world's
    (``time.monotonic()`` s; inf while none), the run's first and last ``seq``, and the world clock
    (s) at its first lemniscate sample."""

    since_s: float
    until_s: float
    first: int
    last: int
    start_t_s: float

    def messages(self, msgs, lo: int | None = None, hi: int | None = None) -> list:
        """Those of ``msgs`` of this run's world with ``lo <= seq <= hi`` (default: the run's)."""
        lo = self.first if lo is None else lo
        hi = self.last if hi is None else hi
        return [m for m in msgs if self.since_s <= m.stamp_s < self.until_s and lo <= m.seq <= hi]


def z_rmse_cm(references, truths, run: Run) -> tuple[float, int]:
    """z RMSE (cm) of truth against reference over one lemniscate run, its ramp left out."""
    refs = {m.seq: m for m in run.messages(references)}
    truth = {m.seq: m.pos_enu_m[2] for m in run.messages(truths)}
    t0 = refs[run.first].t_s
    err = [truth[k] - refs[k].pos_enu_m[2] for k in sorted(set(refs) & set(truth)) if refs[k].t_s >= t0 + RAMP_S]
    return (float(np.sqrt(np.mean(np.square(err)))) * 100 if err else float("nan")), len(err)


def _steps(values: dict) -> dict:
    """seq → |value(seq) − value(seq − 1)| (largest component) where both samples are there."""
    return {k: float(np.max(np.abs(np.asarray(values[k]) - np.asarray(values[k - 1])))) for k in values
            if k - 1 in values}


def analyse(probe, first_run: Run, second_run: Run, swap_seq: int, report: TdrReport,
            stages: dict[str, float] | None = None) -> TdrReport:
    """Fill the flight figures of ``report`` from what ``probe`` (a :class:`runtime.probe.Probe`) saw:
    the first world from its lemniscate to its end (the training, the shadow and the swap happen
    there), the second world's lemniscate. ``stages``: what happened between them → when it began
    (``time.monotonic()`` s), to say in which the missed samples fell."""
    refs, truths = probe.get("reference"), probe.get("truth")
    report.rmse_before_cm, report.cycles_before_samples = z_rmse_cm(refs, truths, first_run)
    report.rmse_after_cm, report.cycles_after_samples = z_rmse_cm(refs, truths, second_run)
    report.improvement = 1.0 - report.rmse_after_cm / report.rmse_before_cm
    spans = {"first": (first_run, first_run.first, 2**62), "second": (second_run, second_run.first, second_run.last)}
    missed, steps, fsteps, stamps = {}, {}, {}, {}
    for name, (run, lo, hi) in spans.items():
        stamps.update({m.seq: m.stamp_s for m in run.messages(probe.get("state"), lo, hi)} if name == "first" else {})
        states = {m.seq for m in run.messages(probe.get("state"), lo, hi)}
        sps = {m.seq: m for m in run.messages(probe.get("setpoint"), lo, hi)}
        good = {k for k, m in sps.items() if m.estimate_source == "estimator"}
        missed[name] = states - good
        report.states += len(states)
        report.states_without_setpoint += len(states - set(sps))
        steps[name] = _steps({k: _force(m) for k, m in sps.items()})
        estimates = run.messages(probe.get("estimate"), lo, hi)
        fsteps[name] = _steps({m.seq: m.f_hat_mps2[2] for m in estimates})
        if name == "first":
            report.f_n_jump_at_swap_mps2 = _steps({m.seq: m.f_n_mps2[2] for m in estimates}).get(swap_seq, float("nan"))
            report.swap_answered = swap_seq in good and swap_seq + 1 in good
    report.missed_setpoints = len(missed["first"]) + len(missed["second"])
    report.missed_near_swap = sum(1 for k in missed["first"] if abs(k - swap_seq) <= 25)
    report.missed_by_phase = {
        "first lemniscate": sum(1 for k in missed["first"] if k <= first_run.last),
        "between (training, shadow, swap)": sum(1 for k in missed["first"] if k > first_run.last),
        "second lemniscate": len(missed["second"])}
    if stages:
        began = sorted(stages.items(), key=lambda kv: kv[1])
        for k in (k for k in missed["first"] if k > first_run.last):
            stage = next((name for name, t in reversed(began) if t <= stamps[k]), "before " + began[0][0])
            key = f"between: {stage}"
            report.missed_by_phase[key] = report.missed_by_phase.get(key, 0) + 1
    report.swap_seq = swap_seq
    near = [v for k, v in steps["first"].items() if abs(k - swap_seq) <= 5]
    normal = [v for k, v in steps["first"].items() if abs(k - swap_seq) > 5] + list(steps["second"].values())
    report.force_step_at_swap_n = max(near) if near else float("nan")
    report.force_step_p50_n = float(np.percentile(normal, 50))
    report.force_step_p99_n = float(np.percentile(normal, 99))
    after = [v for k, v in fsteps["first"].items() if 0 <= k - swap_seq <= 5]
    elsewhere = [v for k, v in fsteps["first"].items() if abs(k - swap_seq) > 5] + list(fsteps["second"].values())
    report.f_hat_step_at_swap_mps2 = max(after) if after else float("nan")
    report.f_hat_step_max_mps2 = max(elsewhere)
    report.f_hat_step_p99_mps2 = float(np.percentile(elsewhere, 99))
    return report


class _Events:
    """Every event of some services of a vehicle, as text."""

    def __init__(self, session, keys, services) -> None:
        from runtime.schema import EventMsg

        self.texts: list[str] = []
        self._subs = [session.declare_subscriber(keys.event(s), lambda smp: self.texts.append(
            EventMsg.from_bytes(smp.payload.to_bytes()).text)) for s in services]

    def wait(self, predicate, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for text in list(self.texts):
                if predicate(text):
                    return text
            time.sleep(0.05)
        raise TimeoutError("no such event")

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def tuned_pdeso(seed: int) -> dict:
    """PD+ESO on the lemniscate near the ground, flown in-process (:func:`sim.runner.fly`) in the demo's scenario
    with its ``seed``, at the paper's gains and at the lemniscate's tuned gains (:data:`sim.tuning.TUNED_GAINS`):
    the z RMSE of the cycles (cm) and the gains, per gain set."""
    from neso.types import OMEGA_O_RPS
    from sim.experiments import PaperConfig
    from sim.flights import run_flight
    from sim.tuning import TUNED_GAINS, ZGains, score, task

    config = PaperConfig()
    out = {}
    for name, gains in (("paper", ZGains.of(ControlConfig(), OMEGA_O_RPS)), ("tuned", TUNED_GAINS["lemniscate"])):
        log = run_flight(task(config, SCENARIO, "pd_eso", {}, gains, seed))
        out[name] = {"gains": gains.to_dict(), "rmse_cm": score(log, config, SCENARIO)}
    return out


def tuned_pdeso_text(t: dict) -> str:
    """One line for :func:`tuned_pdeso`'s figures."""
    if not t:
        return "PD+ESO at the tuned gains: not flown"
    p, q = t["paper"], t["tuned"]
    g = q["gains"]
    if p["rmse_cm"] is None or q["rmse_cm"] is None:
        return f"PD+ESO in-process, same scenario and seed: paper gains {p['rmse_cm']}, tuned {q['rmse_cm']} (crashed)"
    return (f"PD+ESO in-process, same scenario and seed (the live loop cannot fly the tuned ω_o): paper gains "
            f"{p['rmse_cm']:.2f} cm, tuned (k_p {g['kp']:g}, k_d {g['kd']:g}, ω_o {g['omega_o']:g}) {q['rmse_cm']:.2f} cm "
            f"({(q['rmse_cm'] / p['rmse_cm'] - 1) * 100:+.0f} %)")


def fly_tdr_loop(*, hub: str, workdir: str, epochs: int = 100, log=print, on_up=None,
                 fly_after: bool = True, dashboard_port: int | None = None, seed: int = 1,
                 force_offer: bool = False, world: str = "builtin", lockstep_pace: float = 0.0,
                 lemniscate_cycles: int | None = None) -> TdrReport:
    """Run the loop of the module docstring against a ``neso up`` it starts (and stops) on ``hub``.
    ``fly_after`` False: stop once the new network flies (the bench: stage times only; no PD+ESO run).
    ``dashboard_port``: serve the dashboard there to watch the loop (None: no dashboard).
    ``seed``: the world's; ``force_offer``: offer (and promote) even a candidate predicted worse;
    ``world`` px4: PX4 SITL flies the world (it takes off first; the lemniscates are not paired).
    ``lockstep_pace`` > 0: the built-in world in lockstep at most that multiple of real time (0: real time).
    ``lemniscate_cycles``: each lemniscate's (None: the mission's)."""
    from runtime.bus import BusConfig, open_session
    from runtime.launcher import interrupt

    from neso.types import OMEGA_O_RPS
    from sim.tuning import ZGains

    z = ZGains.of(ControlConfig(), OMEGA_O_RPS)
    rec_dir, registry = os.path.join(workdir, "recordings"), os.path.join(workdir, "registry")
    argv = [sys.executable, "-m", "cli.main", "up", "--scenario", "lemniscate_near_ground", "--mission", "hover",
            "--hub", hub, "--recordings-dir", rec_dir, "--registry", registry, "--seed", str(seed)]
    argv += ["--no-dashboard"] if dashboard_port is None else ["--dashboard-port", str(dashboard_port)]
    if lockstep_pace > 0:
        if world != "builtin":
            raise ValueError("only the built-in world flies in lockstep (PX4 keeps wall-clock timeouts)")
        argv += ["--lockstep", "--lockstep-pace", str(lockstep_pace)]
    if world == "px4":
        from cli.paper_px4 import free_px4_instance

        argv += ["--vehicle", "px4", "--px4-instance", str(free_px4_instance())]
    up_log = open(os.path.join(workdir, "neso-up.log"), "w")
    up = subprocess.Popen(argv, stdout=up_log, stderr=subprocess.STDOUT, start_new_session=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    session = open_session(BusConfig(connect=(hub,)))
    try:
        loop = _Loop.watch(session, log, registry, world, lemniscate_cycles)
        loop.report.gains = z.to_dict()
        loop.report.lockstep_pace = lockstep_pace
        try:
            if on_up is not None:
                on_up(up)
            report = loop.run(epochs=epochs, fly_after=fly_after, force_offer=force_offer)
            if fly_after and world == "builtin":
                report.tuned_pdeso = tuned_pdeso(seed)
            return report
        finally:
            loop.close()
    finally:
        session.close()
        interrupt(up, timeout_s=20.0)
        up_log.close()


@dataclass
class _Loop:
    """The stages of :func:`fly_tdr_loop` against a running ``neso up``, filling one report."""

    probe: object
    events: "_Events"
    cmd: object
    params: object
    log: object
    registry: str
    world: str = "builtin"
    report: TdrReport = field(default_factory=TdrReport)
    cycles: int | None = None  # each lemniscate's (None: the mission's)

    @property
    def clock(self) -> str:
        """How the world's clock runs: "lockstep" or "real time"."""
        return "lockstep" if self.report.lockstep_pace > 0 else "real time"

    @classmethod
    def watch(cls, session, log, registry: str, world: str = "builtin", cycles: int | None = None) -> "_Loop":
        """The loop flying on ``session``'s bus; ``cycles``: each lemniscate's (None: the mission's)."""
        from flight.mission import MissionConfig
        from runtime.client import command, set_params
        from runtime.probe import Probe
        from runtime.schema import Keys

        keys = Keys("uav1")
        probe = Probe(session, keys.vehicle, ("state", "truth", "estimate", "setpoint", "reference", "network",
                                              "recording"))
        events = _Events(session, keys, ("trainer", "estimator", "recorder"))

        def cmd(service, command_name, timeout_s=5.0, **args):
            return command(session, keys, service, command_name, args, timeout_s=timeout_s)

        def params(service, timeout_s=5.0, **values):
            return set_params(session, keys, service, values, timeout_s)
        report = TdrReport(world=world, lemniscate_cycles=cycles or MissionConfig().lemniscate_cycles)
        return cls(probe, events, cmd, params, log, registry, world=world, cycles=cycles, report=report)

    def close(self) -> None:
        self.events.close()
        self.probe.close()

    def run(self, *, epochs: int, fly_after: bool, force_offer: bool) -> TdrReport:
        report = self.report
        self.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > 100, 60.0)
        if self.world == "px4":
            self.take_off_with_px4()
        first_run, t_stop = self.record_first_lemniscate()
        done, t_train = self.train(epochs, force_offer)
        _registry_figures(self.registry, report)
        report.offered = "offer accepted" in done
        if not report.offered:  # predicted to fly worse (or refused): the base network flies on
            self.log(f"candidate not offered: {done}")
            if fly_after:
                self.fly_base_again(first_run)
                self.fly_pdeso()
            return report
        t_offered = time.monotonic()
        swap_seq, t_promote, t_promoted = self.shadow_and_promote(force_offer)
        report.stage_s = {"stop recording": t_train - t_stop, "train job (dataset, train, certify, predict, store, offer)":
                          t_offered - t_train, "promote": t_promoted - t_promote,
                          "recording stopped -> promoted (without the 2 s shadow)":
                          (t_offered - t_stop) + (t_promoted - t_promote)}
        report.stage_s.update({f"trainer {k}": float(v) for k, v in _stage_times(done).items()})
        if fly_after:
            self.log("promoted; flying the lemniscate again, " + ("in the same world as the first" if self.world == "builtin"
                                                                   else "in the world flying on (not paired)"))
            since = self.new_world()
            self.cmd("recorder", "start")
            second_run = fly_lemniscate(self.probe, self.cmd, since, self.clock, self.cycles)
            report.lemniscate_start_t_s.append(second_run.start_t_s)
            report.canary = self.probe.get("network")[-1].canary.get("last", "")
            analyse(self.probe, replace(first_run, until_s=second_run.since_s), second_run, swap_seq, report,
                    {"recording stopped": t_stop, "training": t_train, "shadow": t_offered, "promote": t_promote,
                     "promoted": t_promoted})
            self.fly_pdeso()
        return report

    def fly_pdeso(self) -> None:
        """The lemniscate once more with PD+ESO (the estimator's ``eso`` pathway) at the same gains, in its own world
        (paired with the others in the built-in world); the network's pathway back after it."""
        reply = self.params("estimator", pathway="eso")
        if not reply.ok:
            raise RuntimeError(f"the estimator refused the eso pathway: {reply.error}")
        self.log("flying the lemniscate with PD+ESO at the same gains")
        run = fly_lemniscate(self.probe, self.cmd, self.new_world(), self.clock, self.cycles)
        self.report.lemniscate_start_t_s.append(run.start_t_s)
        self.report.rmse_pdeso_cm, self.report.pdeso_samples = z_rmse_cm(self.probe.get("reference"),
                                                                          self.probe.get("truth"), run)
        self.params("estimator", pathway="neural_eso")

    def new_world(self) -> float:
        """Where a lemniscate run's samples begin (a stamp, s), 1 s from now so that what went before (a swap just
        made, and the samples after it that show it answered) stays in the run before: the built-in world restarted
        with its seed (the runs paired); with PX4 the world flies on (PX4 would not follow a restart)."""
        time.sleep(1.0)
        if self.world == "builtin":
            return restart_world(self.probe, self.cmd)
        return self.probe.get("state")[-1].stamp_s

    def take_off_with_px4(self) -> None:
        """As an operator does with PX4: its "Ready for takeoff" (offboard and arm are refused until then, so each
        is asked once a second), then the controller's take-off to its hover."""
        self.log("PX4: waiting for it to be ready, then offboard, arm and take off")
        for service, name in (("px4_gateway", "offboard_start"), ("px4_gateway", "arm")):
            deadline = time.monotonic() + 120.0
            while not (reply := self.cmd(service, name, timeout_s=8.0)).ok:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"PX4 refused {name} for 120 s: {reply.message}")
                time.sleep(1.0)
        for name in ("arm", "takeoff"):
            reply = self.cmd("controller", name)
            assert reply.ok, reply.message
        self.probe.wait_for("truth", lambda m: m.pos_enu_m[2] > 0.9, 30.0)
        time.sleep(2.0)

    def record_first_lemniscate(self) -> tuple[Run, float]:
        """The base network flies the lemniscate, recorded; the recording is stopped (and its path kept)."""
        probe, cmd = self.probe, self.cmd
        self.log("flying the lemniscate under Neural-ESO with the base network, recording")
        first_run = fly_lemniscate(probe, cmd, self.new_world(), self.clock, self.cycles)
        self.report.lemniscate_start_t_s.append(first_run.start_t_s)
        path = probe.wait_for("recording", lambda m: m.recording and m.path and m.stamp_s > first_run.since_s, 5.0).path
        t_stop = time.monotonic()
        reply = cmd("recorder", "stop")
        assert reply.ok, reply.message
        probe.wait_for("recording", lambda m: not m.recording and m.stamp_s > t_stop, 10.0)
        self.report.recording = path
        return first_run, t_stop

    def train(self, epochs: int, force_offer: bool) -> tuple[str, float]:
        """The trainer's TDR job on the recording; its done event and when it was asked."""
        self.log(f"recorded {self.report.recording}; training TDR from it")
        t_train = time.monotonic()
        reply = self.cmd("trainer", "train", recordings=[self.report.recording], epochs=epochs, force_offer=force_offer)
        assert reply.ok, reply.message
        job = reply.message.split()[1]
        done = self.events.wait(lambda t: t.startswith(f"job {job} done") or t.startswith(f"job {job} failed"), 300.0)
        self.report.trainer_summary = done
        if not done.startswith(f"job {job} done"):
            raise RuntimeError(f"training failed: {done}")
        return done, t_train

    def fly_base_again(self, first_run: Run) -> None:
        """Nothing was offered: the same network flies the same world again (the pairing's own noise)."""
        report, probe = self.report, self.probe
        second_run = fly_lemniscate(probe, self.cmd, self.new_world(), self.clock, self.cycles)
        first_run = replace(first_run, until_s=second_run.since_s)
        report.lemniscate_start_t_s.append(second_run.start_t_s)
        refs, truths = probe.get("reference"), probe.get("truth")
        report.rmse_before_cm, report.cycles_before_samples = z_rmse_cm(refs, truths, first_run)
        report.rmse_after_cm, report.cycles_after_samples = z_rmse_cm(refs, truths, second_run)
        report.improvement = 1.0 - report.rmse_after_cm / report.rmse_before_cm

    def shadow_and_promote(self, force: bool) -> tuple[int, float, float]:
        """2 s of shadow, then promote; the first sample the candidate flew and the promotion's times."""
        probe, report = self.probe, self.report
        cand = probe.wait_for("network", lambda m: m.candidate.get("state") == "shadow", 5.0).candidate
        report.network_id = cand["id"]
        self.log(f"candidate {cand['id']} in shadow; promoting")
        time.sleep(2.0)  # shadow: predicting beside the active network
        shadow = probe.get("network")[-1]
        report.shadow_error_rms_mps2 = shadow.shadow_error_rms_mps2
        report.active_error_rms_mps2 = shadow.candidate.get("active_error_rms_mps2", float("nan"))
        before = probe.get("estimate")[-1].seq
        t_promote = time.monotonic()
        reply = self.cmd("estimator", "promote", force=force)
        assert reply.ok, reply.message
        probe.wait_for("estimate", lambda m: m.network_id == cand["id"] and m.seq > before, 5.0)
        t_promoted = time.monotonic()
        swap_seq = min(m.seq for m in probe.get("estimate") if m.network_id == cand["id"])
        return swap_seq, t_promote, t_promoted


def _registry_figures(registry: str, report: TdrReport) -> None:
    """The candidate's id, certificate and closed-loop prediction from the registry's sidecar."""
    import glob

    sidecars = sorted(glob.glob(os.path.join(registry, "*", "*.json")), key=os.path.getmtime)
    if sidecars:
        with open(sidecars[-1]) as f:
            info = json.load(f)
        report.network_id = info.get("id", "")
        report.predicted = info.get("predicted", {})
        report.certificate = info.get("certificate", {})


def restart_world(probe, cmd) -> float:
    """Restart the simulated world (same scenario, same seed); the stamp of its first state."""
    t_cmd = time.monotonic()
    reply = cmd("source", "scenario", name=SCENARIO)
    assert reply.ok, reply.message
    first = probe.wait_for("state", lambda m: m.stamp_s > t_cmd and m.seq < 50, 10.0)
    return min(m.stamp_s for m in probe.get("state") if m.stamp_s > t_cmd and m.seq <= first.seq)


def fly_lemniscate(probe, cmd, since_s: float, clock: str = "real time", cycles: int | None = None) -> Run:
    """In the world that began at ``since_s``: the lemniscate, started by the controller at the world's
    ``PAIRED_START_T_S`` (sent with the command, so its latency does not move the start: under load a command sent
    when the clock got there began 11 samples late), and wait until it is over. ``clock``: "real time" or
    "lockstep" (when the command is sent: :data:`COMMAND_FROM_T_S`); ``cycles``: the lemniscate's (None: the mission's)."""
    # sent ahead: the controller has begun this world's flight (a new world restarts its mission) and the command's
    # latency, up to the time left, no longer decides when the lemniscate begins
    probe.wait_for("state", lambda m: m.stamp_s >= since_s and m.t_s >= COMMAND_FROM_T_S[clock], 30.0)
    reply = cmd("controller", "lemniscate", at_t_s=PAIRED_START_T_S, **({} if cycles is None else {"cycles": cycles}))
    assert reply.ok, reply.message
    ours = lambda m: m.stamp_s >= since_s  # noqa: E731
    first = probe.wait_for("reference", lambda m: ours(m) and m.segment == "lemniscate", 30.0)
    probe.wait_for("reference", lambda m: ours(m) and m.segment != "lemniscate" and m.seq > first.seq, 90.0)
    refs = [m for m in probe.get("reference") if ours(m)]
    runs = lemniscate_runs(refs)
    assert len(runs) == 1, f"one lemniscate run expected in the world that began at {since_s}: {runs}"
    start_t_s = next(m.t_s for m in refs if m.seq == runs[0][0])
    return Run(since_s, math.inf, runs[0][0], runs[0][1], start_t_s)


def _stage_times(summary: str) -> dict:
    """The trainer's ``stage x.xx s`` figures out of its job summary."""
    import re

    return {m.group(1): float(m.group(2)) for m in re.finditer(r"(dataset|train|certify|predict|store|offer) ([0-9.]+) s",
                                                               summary)}


def free_loopback_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(args) -> int:
    from flight.controller import MAX_LEMNISCATE_CYCLES

    if args.lockstep_pace < 0 or (args.lockstep_pace and args.world != "builtin"):
        print(f"neso demo tdr: --lockstep-pace {args.lockstep_pace:g}: a multiple of real time ≥ 0, with the built-in "
              "world only (PX4 keeps wall-clock timeouts)", flush=True)
        return 2
    if args.lemniscate_cycles is not None and not 1 <= args.lemniscate_cycles <= MAX_LEMNISCATE_CYCLES:
        print(f"neso demo tdr: --lemniscate-cycles {args.lemniscate_cycles}: 1-{MAX_LEMNISCATE_CYCLES}", flush=True)
        return 2
    if args.world == "px4":
        from sim.px4_sitl import missing_px4

        if missing_px4():
            print(f"neso demo tdr: {missing_px4()}", flush=True)
            return 2
    hub = args.hub or f"tcp/127.0.0.1:{free_loopback_port()}"
    workdir = args.workdir or tempfile.mkdtemp(prefix="neso-tdr-")
    os.makedirs(workdir, exist_ok=True)
    report = fly_tdr_loop(hub=hub, workdir=workdir, epochs=args.epochs, dashboard_port=args.dashboard_port or None,
                          seed=args.seed, force_offer=args.force_offer, world=args.world,
                          lockstep_pace=args.lockstep_pace, lemniscate_cycles=args.lemniscate_cycles)
    print("\n".join(report.lines()))
    print(f"recordings, registry and the neso up log are in {workdir}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(asdict(report), f, indent=1)
    return 0
