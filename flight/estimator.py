"""The estimator's step object: Neural-ESO with live pathway and Lipschitz bound (service ``estimator``).

The step object (:class:`EstimatorCore`) runs :class:`neso.estimator.NeuralESO` on each state
sample with the control that acted over the period before it (the setpoint answering the
previous sample; in lockstep it waits for that setpoint, in real time it takes the newest).
Live parameters:

- ``pathway`` (``neural_eso``, ``eso``, ``nn``, ``none``): switched bumplessly at the next sample.
- ``lipschitz_bound`` (L_N in physical units, (m/s²) per unit z — what the stability
  certificate needs): the network trained for that bound if one is in the network's directory
  (same training data as the loaded one), otherwise the loaded network with its layers scaled
  down until its exact physical certificate meets the bound. A bound above the one the loaded
  network states, with no network for it on disk, is refused: scaling can only flatten a
  network. The broadcast says which was done.
- ``omega_o_rps``: shown so watchers know the observer bandwidth; read-only (its range is the
  start-up value), since it is start-up config (``--omega-o``).

The stability certificate is checked here, where the change is applied: a change of L_N (or a
pathway that would fly an uncertified network, or a promotion) whose certificate fails for the
z gains the controller flies (from its parameter broadcasts) and this ω_o is refused with the
margin in the reason, unless the request carries ``override: true`` — then it is applied and
an event says so (the recorder puts it in the flight's ``.rrd``). At start-up a network whose
certificate fails is not flown (the observer flies alone) unless ``--allow-uncertified``.
``NetworkMsg.certificate`` carries the verdict for what flies; the dashboard only shows it.

Network hot swap (commands on ``neso/<v>/cmd/estimator``; each replies ok=False with the reason
when refused, and a refusal leaves the active network flying):

- ``offer {path, predicted?}``: a candidate network file (normally from the registry) goes through the gate
  (:func:`flight.hotswap.gate`: readable, finite, same layer shapes, certificate within its bound
  in physical units, validation loss present, trained for this vehicle). A passed one runs in
  **shadow**: it predicts beside the active network every sample, and its RMS error against
  the flown f̂ (z axis, last 5 s) is in ``NetworkMsg.shadow_error_rms_mps2``; the active
  network's own error over the same samples is ``candidate["active_error_rms_mps2"]``.
- ``promote [force]``: the candidate becomes the active network at the next sample; Δf̂ absorbs
  the step so f̂ is continuous (:meth:`neso.estimator.NeuralESO.set_network`). The active one
  becomes ``previous``. Refused without ``force: true`` when its certificate fails or when the
  trainer's closed-loop prediction (``offer``'s ``predicted``) says it flies worse than the active network
  or no better than PD+ESO at the flown gains.
- the **canary** (:class:`flight.hotswap.Canary`): after a promotion the z tracking error (state
  against the controller's reference, same ``seq``) is compared with the error before it on the
  same mission segment; worse by more than ``--canary-margin`` over ``--canary-window`` samples
  and the previous network flies again at the next sample, with an event saying why.
- ``rollback``: the previous network flies again, the same bumpless way.
- ``reject``: drop the candidate.

A retried command is done once: ``runtime.client.command`` sends a request id and the node
answers a repeat with the first answer (:class:`runtime.node.AnsweredOnce`), so a second
rollback never undoes the first.

``NetworkMsg`` on ``neso/<v>/network``: once a second and on every change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from flight import forget_older
from flight.hotswap import Canary, CanaryConfig, GateVerdict, ShadowError, gate
from flight.mission import segment_reference_bounds
from flight.ratecheck import RateCheck
from neso.certificate import FlightCertificate, LoopPlant, NetworkSlopes, ReferenceBounds, flight_certificate
from neso.control import ControlConfig, PositionController
from neso.eso import EsoConfig
from neso.estimator import AppliedControl, NeuralESO, NeuralEsoConfig
from neso.features import FeatureBuilder
from neso.netfile import NetworkFileError, load_network
from neso.network import LipschitzMLP
from neso.types import LOOP_PERIOD_S, OMEGA_O_RPS, PATHWAYS, VehicleModel
from runtime.options import option, rate_of_period
from runtime.params import Param, Refusal
from runtime.schema import EstimateMsg, NetworkMsg, ReferenceMsg, SetpointMsg, StateMsg, state_measurement, vec

DEFAULT_NETWORK = "networks/base.safetensors"
PROJECT_ROOT = Path(__file__).resolve().parents[1]  # the checkout: where networks/ ships
SHADOW_WINDOW = 250  # samples: 5 s at 50 Hz
MAX_NETWORK_FILE_BYTES = 10_000_000
PRIOR_PATHWAYS = ("neural_eso", "nn")  # pathways that fly the network
SEGMENT_BOUNDS = segment_reference_bounds()  # the z reference of each mission segment: what the |e_z| bound is for


@dataclass(frozen=True)
class EstimatorConfig:
    """``network``: the network file flown (``""``: none; nn/neural_eso then predict 0).
    ``network_dir``: where networks trained for other bounds are looked for (default: the
    network's own directory). ``allow_uncertified``: fly a start-up network whose certificate
    fails. ``mass_kg``: the vehicle's mass until the controller says otherwise. ``canary``: the
    rollback watch after a promotion."""

    network: str = option(DEFAULT_NETWORK, help="network file flown ('' for none)")
    network_dir: str = option("", help="networks trained for other L_N ('': the network's own directory)")
    pathway: str = option("neural_eso", help="which pathways make f̂", choices=PATHWAYS)
    omega_o_rps: float = option(OMEGA_O_RPS, flag="--omega-o", unit="rad/s", help="observer bandwidth")
    dt_s: float = option(LOOP_PERIOD_S, flag="--rate", unit="Hz", cli=rate_of_period(),
                         help="sample rate (must match the source's)")
    lockstep: bool = False
    allow_uncertified: bool = option(False, help="fly a start-up network whose stability certificate fails "
                                                 "(recorded as an event)")
    mass_kg: float = option(VehicleModel().mass_kg, unit="kg", help="the vehicle's mass, as the controller flies it "
                            "(the certificate's loop gain; a network with a thrust input in newtons is for one mass); "
                            "the controller's live parameter updates it")
    canary: CanaryConfig = option(default_factory=CanaryConfig, nested=True)


def estimator_params(config: EstimatorConfig, bound_phys: float) -> tuple[Param, ...]:
    return (
        Param("pathway", config.pathway, str, "which pathways make f̂", choices=PATHWAYS),
        Param("lipschitz_bound", bound_phys, float, "L_N of the network flown (physical)", "(m/s²)/unit z",
              lo=1e-6, hi=1e3),
        Param("omega_o_rps", config.omega_o_rps, float, "observer bandwidth (start-up config: read-only)", "rad/s",
              lo=config.omega_o_rps, hi=config.omega_o_rps),
    )


BOUND_MATCH_REL = 5e-4  # an L_N typed as shown (4 significant digits) finds the network trained for it


def _same_bound(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=BOUND_MATCH_REL)


class NetworkChoice:
    """Which network flies at a given physical L_N: one trained for it on disk, or the loaded one scaled."""

    def __init__(self, loaded: LipschitzMLP | None, source: str, directory: str | None) -> None:
        self.loaded, self.source = loaded, source
        self.trained: dict[float, tuple[LipschitzMLP, str]] = {}
        self.skipped: list[str] = []
        if loaded is None:
            return
        directory = directory or str(Path(source).parent)
        if not Path(directory).is_dir():
            return
        family = (loaded.metadata.get("training_data", ""), loaded.feature_set.key)
        for path in sorted(Path(directory).glob("*.safetensors")):
            try:
                net = load_network(path, expected_outputs=loaded.n_outputs)
            except NetworkFileError as exc:
                self.skipped.append(f"{path}: {exc}")
                continue
            if (net.metadata.get("training_data", ""), net.feature_set.key) == family:
                self.trained.setdefault(net.lipschitz_bound_physical(), (net, str(path)))

    def refusal(self, bound: float) -> str | None:
        if self.loaded is None:
            return "no network is loaded, so there is no L_N to set"
        if any(_same_bound(bound, b) for b in self.trained) or bound <= self.loaded.lipschitz_bound_physical() * (1 + 1e-9):
            return None
        return (f"L_N={bound:.4g} is above the {self.loaded.lipschitz_bound_physical():.4g} the loaded network states, "
                f"and no network trained for {bound:.4g} on the same data is on disk "
                f"(have: {[round(b, 4) for b in sorted(self.trained)]})")

    def network_for(self, bound: float) -> tuple[LipschitzMLP, str]:
        """(network, what was done) for L_N = ``bound`` physical (call only if :meth:`refusal` is None)."""
        for b, (net, path) in self.trained.items():
            if _same_bound(b, bound):
                if b > bound and net.certified_lipschitz() > bound:  # never fly more than asked
                    net = net.scaled_to_bound(bound, "physical")
                return net, f"loaded {path}, trained for L_N={b:.4g} (certified {net.certified_lipschitz_physical():.4g} " \
                            f"physical, {net.certified_lipschitz_normalised():.4g} normalised)"
        net = self.loaded.scaled_to_bound(bound, "physical")
        return net, (f"no network trained for L_N={bound:.4g} on disk: scaled {self.source} down to certified "
                     f"{net.certified_lipschitz_physical():.4g} physical ({net.certified_lipschitz_normalised():.4g} "
                     "normalised)")


class EstimatorCore:
    """The pure step object: :meth:`on_setpoint`, :meth:`on_state` and :meth:`on_reference` return the
    estimates to publish; :attr:`events` collects what an operator must be told."""

    def __init__(self, config: EstimatorConfig, network: LipschitzMLP | None, choice: NetworkChoice,
                 vehicle: str = "uav1", *, clock: Callable[[], float]) -> None:
        self.config = config
        self.clock = clock
        self.choice = choice
        self.vehicle = vehicle
        control = ControlConfig(dt_s=config.dt_s, vehicle=VehicleModel(mass_kg=config.mass_kg))
        self.gains_z = (control.kp[2], control.kd[2])  # until the controller says otherwise
        self.plant = LoopPlant.of(control)
        self.events: list[tuple[str, str]] = []
        self.network_id = network.metadata.get("id", "unnamed") if network is not None else "none"
        self.active_info = _describe(network, "file", choice.source)
        self.candidate: tuple[LipschitzMLP, dict] | None = None
        self.previous: tuple[LipschitzMLP | None, dict] | None = None
        self.shadow = ShadowError(SHADOW_WINDOW)
        self.active_shadow = ShadowError(SHADOW_WINDOW)  # the active network's error, same samples
        self._shadow_features: FeatureBuilder | None = None
        self.swapped = False  # a network from an offer is flying (the L_N parameter no longer picks networks)
        self.bound_in_force: float | None = None  # an L_N the operator set: what flies may use up to it
        self.changes = 0  # bumped on every network change, so the adapter publishes NetworkMsg at once
        self.canary = Canary(config.canary)
        self.canary_last = ""
        self._segment = ("", 0)  # the reference's segment and its run number
        self._meas_z: dict[int, float] = {}
        self.estimator = NeuralESO(NeuralEsoConfig(eso=EsoConfig(omega_o_rps=config.omega_o_rps, dt_s=config.dt_s),
                                                   pathway=config.pathway), network)
        self._hover = PositionController(control).hover_output().applied
        self._applied: dict[int, AppliedControl] = {}
        self._latest_applied: AppliedControl | None = None
        self._waiting: list[StateMsg] = []
        self._last_seq = -1
        self._last_output: EstimateMsg | None = None
        self.warm_ticks = 0
        self.rate_check = RateCheck("estimator", config.dt_s)

    # -- the certificate -------------------------------------------------------------------
    def certificate_of(self, net: LipschitzMLP | None, gains_z: tuple[float, float] | None = None,
                       bound: float | None = None) -> FlightCertificate:
        """The certificate of flying ``net`` (its exact physical slopes by input role; none without one) under an L_N
        ``bound`` the operator set on its state inputs (None: the network's own figure counts)."""
        kp, kd = gains_z or self.gains_z
        return network_certificate(net, kp, kd, self.config.omega_o_rps, self.plant, bound=bound)

    def certificate(self) -> FlightCertificate:
        """The verdict for the network flying now, under the L_N the operator set (a bound above the certificate
        is not certified even while the network found for it stays inside)."""
        net = self.estimator.network
        return self.certificate_of(net, bound=self.bound_in_force if net is not None else None)

    def set_gains(self, kp_z: float, kd_z: float, mass_kg: float | None = None) -> str | None:
        """The controller's z gains (and vehicle mass) changed (its parameter broadcast); a note if the certificate
        now fails."""
        self.gains_z = (float(kp_z), float(kd_z))
        if mass_kg is not None:
            self.plant = LoopPlant(float(mass_kg), self.plant.force_rate_limit_nps, self.plant.max_tilt_rad)
        self.changes += 1
        cert = self.certificate()
        return None if cert.holds else f"controller gains or mass changed: {cert.text()}"

    def prepare(self, values: dict) -> None:
        """Warm the certificate cache for the verdict :meth:`check` will ask of ``values`` (and the flying one's): its
        SDPs (0.35 s on an idle core for a new L_N) are solved here, outside the node lock, not in the loop's way."""
        self.certificate()
        asked = self._asked(values) if values else None  # {}: the flying one's only
        if isinstance(asked, tuple):
            self.certificate_of(asked[0], bound=asked[1])

    # -- live parameters ----------------------------------------------------------------
    def _asked(self, values: dict) -> str | tuple[LipschitzMLP, float | None] | None:
        """What the live parameters ``values`` ask to fly: a refusal (text), or the network and the L_N bound (None: its
        own) whose certificate decides, or None when no certificate does (no network, or a pathway without a prior)."""
        current = self.estimator.network
        net = current
        if current is not None and not _same_bound(values["lipschitz_bound"], bound_phys(current)):
            if self.swapped:
                return (f"the active network {self.network_id} came from an offer: its L_N "
                        f"{bound_phys(current):.4g} is fixed (train another, or rollback)")
            refusal = self.choice.refusal(values["lipschitz_bound"])
            if refusal:
                return refusal
            net, _ = self.choice.network_for(values["lipschitz_bound"])
        if net is None or values["pathway"] not in PRIOR_PATHWAYS:
            return None
        # a new L_N: the bound asked for must be certified, not only the network found for it
        return net, (values["lipschitz_bound"] if net is not current else None)

    def check(self, values: dict) -> str | Refusal | None:
        asked = self._asked(values)
        if not isinstance(asked, tuple):
            return asked
        cert = self.certificate_of(asked[0], bound=asked[1])
        return None if cert.holds else Refusal(cert.text(), overridable=True)

    def apply(self, changed: dict) -> str:
        notes = []
        if "pathway" in changed:
            self.estimator.set_pathway(changed["pathway"])
            notes.append(f"pathway {changed['pathway']}")
        if "lipschitz_bound" in changed and self.choice.loaded is not None and not self.swapped:
            net, note = self.choice.network_for(changed["lipschitz_bound"])
            self.estimator.set_network(net)
            loaded = self.choice.loaded.lipschitz_bound_physical()
            self.bound_in_force = None if _same_bound(changed["lipschitz_bound"], loaded) else changed["lipschitz_bound"]
            self.network_id = f"{net.metadata.get('id', 'unnamed')}@L{changed['lipschitz_bound']:.4g}"
            path = next((p for b, (_, p) in self.choice.trained.items()  # the file trained for it (maybe scaled by
                         if _same_bound(b, changed["lipschitz_bound"])), None)  # a hair to what was typed)
            self.active_info = _describe(net, "scaled" if path is None else "file", path or self.choice.source,
                                         self.network_id)
            self.changes += 1
            notes.append(note)
        return "; ".join(notes)

    # -- network hot swap ---------------------------------------------------------------
    def check_offer(self, path: str) -> GateVerdict:
        """Read and gate a candidate file (touches no estimator state but the active network; warms the certificate
        cache with the candidate's)."""
        try:
            size = Path(path).stat().st_size
            if size > MAX_NETWORK_FILE_BYTES:
                return GateVerdict(None, f"network file {path} is {size} bytes (> {MAX_NETWORK_FILE_BYTES})")
            data = Path(path).read_bytes()
        except OSError as exc:
            return GateVerdict(None, f"cannot read {path}: {exc.strerror or exc}")
        verdict = gate(data, active=self.estimator.network, vehicle=self.vehicle)
        if verdict.passed:  # its certificate's SDP solved here, outside the node lock (0.4-1 s: the loop must not wait)
            self.certificate_of(verdict.network)
        return verdict

    def accept(self, verdict: GateVerdict, path: str, predicted: dict | None = None) -> str:
        """Put a passed candidate in shadow (replacing any earlier candidate). ``predicted``: the
        trainer's closed-loop prediction (RMSE of the active and the candidate on the recorded flight)."""
        net = verdict.network
        info = _describe(net, "registry", path)
        cert = self.certificate_of(net)
        info.update(state="shadow", certificate=cert.to_dict(), **{k: v for k, v in verdict.findings.items() if k not in info})
        if predicted:
            info["predicted"] = dict(predicted)
        self.candidate = (net, info)
        self.shadow = ShadowError(SHADOW_WINDOW)
        self.active_shadow = ShadowError(SHADOW_WINDOW)
        self._shadow_features = None  # built at the next sample, from that sample
        self.changes += 1
        pred = _predicted_text(info.get("predicted"))
        return (f"candidate {info['id']} in shadow ({verdict.findings.get('layers')}, {net.feature_set.key}, "
                f"val_loss {info['val_loss']}; {cert.text()}{pred})")

    def promote(self, force: bool = False) -> tuple[bool, str]:
        if self.candidate is None:
            return False, "no candidate to promote (offer one first)"
        net, info = self.candidate
        cert = self.certificate_of(net)
        predicted = info.get("predicted") or {}
        change, vs_pdeso = predicted.get("change"), predicted.get("change_vs_pdeso")
        worse = isinstance(change, (int, float)) and change >= 0
        no_better = isinstance(vs_pdeso, (int, float)) and vs_pdeso >= 0
        if not force:
            if not cert.holds:
                return False, f"candidate {info['id']}: {cert.text()} (promote with force=true to fly it anyway)"
            if worse or no_better:
                what = "to fly worse" if worse else "no better than PD+ESO at the flown gains"
                return False, (f"candidate {info['id']} is predicted {what}{_predicted_text(predicted)}"
                               " (promote with force=true to fly it anyway)")
        shadow = self.shadow.rms()
        self.previous = (self.estimator.network, self.active_info)
        self.estimator.set_network(net)
        info = {k: v for k, v in info.items() if k != "state"}
        self.active_info, self.network_id, self.candidate, self.swapped = info, info["id"], None, True
        self.bound_in_force = None
        self.changes += 1
        self.canary.arm()
        self.canary_last = f"armed at the promotion of {info['id']}"
        forced = " by force" if force and (not cert.holds or worse or no_better) else ""
        shadow_text = f"{shadow:.4g} m/s²" if shadow >= 0 else "none (no shadow samples yet)"
        return True, (f"promoted {info['id']}{forced} (shadow error {shadow_text}; {cert.text()}); previous "
                      f"{self.previous[1]['id']}; the canary watches the next {self.config.canary.window_samples} "
                      "comparable samples")

    def rollback(self) -> tuple[bool, str]:
        if self.previous is None:
            return False, "no previous network to roll back to"
        net, info = self.previous
        self.previous = (self.estimator.network, self.active_info)
        self.estimator.set_network(net)
        self.active_info, self.network_id = info, info["id"]
        self.swapped = info.get("source") == "registry"
        self.bound_in_force = None
        self.changes += 1
        self.canary.disarm()
        return True, f"rolled back to {info['id']}; previous {self.previous[1]['id']}"

    def reject(self) -> tuple[bool, str]:
        if self.candidate is None:
            return False, "no candidate to reject"
        cid = self.candidate[1]["id"]
        self.candidate = None
        self.changes += 1
        return True, f"candidate {cid} dropped"

    def network_msg(self) -> NetworkMsg:
        candidate = {}
        if self.candidate is not None:
            candidate = dict(self.candidate[1], shadow_samples=self.shadow.samples,
                             active_error_rms_mps2=self.active_shadow.rms())
        verdict = self.certificate()
        cert = verdict.to_dict()
        segment = self._segment[0]
        bound, pdeso = verdict.bound_for_cm(SEGMENT_BOUNDS.get(segment, ReferenceBounds.envelope()))
        cert.update(pathway=self.estimator.pathway, covers=self.estimator.pathway in ("neural_eso", "eso", "none"),
                    segment=segment, segment_bound_cm=bound if math.isfinite(bound) else None,
                    segment_pdeso_bound_cm=pdeso if math.isfinite(pdeso) else None)
        return NetworkMsg(stamp_s=self.clock(), seq=max(self._last_seq, 0), active=self.active_info,
                          candidate=candidate,
                          previous=self.previous[1] if self.previous is not None else {},
                          shadow_error_rms_mps2=self.shadow.rms() if self.candidate is not None else -1.0,
                          certificate=cert,
                          canary={"armed": self.canary.armed, "last": self.canary_last,
                                  "window_samples": self.config.canary.window_samples,
                                  "margin": self.config.canary.margin})

    # -- samples ------------------------------------------------------------------------
    def on_setpoint(self, sp: SetpointMsg, now_s: float) -> list[EstimateMsg]:
        applied = AppliedControl(acc_cmd_enu_mps2=np.array(sp.acc_cmd_enu_mps2), thrust_n=sp.thrust_n)
        self._applied[sp.seq] = applied
        self._latest_applied = applied
        forget_older(self._applied, sp.seq)
        out = []
        for waiting in [s for s in self._waiting if s.seq - 1 in self._applied]:
            if waiting.seq > self._last_seq:  # not passed by a newer one meanwhile
                out += self._process(waiting, now_s)
        return out

    def on_reference(self, ref: ReferenceMsg) -> None:
        """The controller's reference for sample ``seq``: the tracking error feeds the canary."""
        z = self._meas_z.pop(ref.seq, None)
        forget_older(self._meas_z, ref.seq)
        segment, run = self._segment
        if ref.segment != segment:
            self._segment = (ref.segment, run + 1)
        if z is None:
            return
        verdict = self.canary.observe(ref.segment, self._segment[1], z - ref.pos_enu_m[2])
        if verdict is None:
            return
        text = verdict.text(ref.seq)
        self.canary_last = text
        self.changes += 1
        if not verdict.rollback:
            self.events.append(("info", text))
            return
        ok, message = self.rollback()
        self.events.append(("warning", f"{text}: {message}" if ok else f"{text}; {message}"))

    def on_state(self, state: StateMsg, now_s: float) -> list[EstimateMsg]:
        if state.seq == self._last_seq and self._last_output is not None:
            return [self._last_output]  # a re-sent sample: answer it again
        if 0 < state.seq < self._last_seq:
            return []
        if self.config.lockstep and state.seq > 0 and self._last_seq >= 0 and state.seq - 1 not in self._applied:
            self._waiting.append(state)  # lockstep: the control of the previous period is still on its way
            return []
        return self._process(state, now_s)

    def _process(self, state: StateMsg, now_s: float) -> list[EstimateMsg]:
        meas = state_measurement(state)
        if self._last_seq < 0 or state.seq < self._last_seq:  # first sample, or a new flight
            applied = self._hover if state.seq == 0 else (self._latest_applied or self._hover)
            self._applied.clear()
            self.estimator.reset(meas, applied.thrust_n)
            self._shadow_features = None
            self.warm_ticks = 0
        else:
            applied = self._applied.get(state.seq - 1) or self._latest_applied or self._hover
        if self._waiting:  # lockstep only: nothing to do on real time's path
            self._drop_waiting_passed_by(state.seq)
        self._last_seq = state.seq
        wrong_rate = self.rate_check.observe(state.seq, state.t_s)
        if wrong_rate:
            self.events.append(wrong_rate)
        self._meas_z[state.seq] = state.pos_enu_m[2]
        est = self.estimator.update(meas, applied)
        self.warm_ticks += 1
        if self.candidate is not None:
            self._shadow(meas, applied, est)
        self._last_output = EstimateMsg(
            seq=state.seq, stamp_s=self.clock(), t_s=state.t_s, f_hat_mps2=vec(est.f_hat), f_n_mps2=vec(est.f_n),
            delta_f_hat_mps2=vec(est.delta_f_hat), z=vec(est.z), pathway=est.pathway, network_id=self.network_id,
            warm_ticks=self.warm_ticks)
        return [self._last_output]

    def _drop_waiting_passed_by(self, seq: int) -> None:
        """Forget the states still waiting for their setpoint that sample ``seq`` passed: the controller flew them on
        its own. Left waiting, one would hold up every later state that arrives before its own setpoint."""
        if seq == 0:
            self._waiting.clear()  # a new flight: what waited was the last one's
        stale = [s.seq for s in self._waiting if s.seq < seq]
        self._waiting = [s for s in self._waiting if s.seq > seq]
        if stale:
            self.events.append(("warning", f"lockstep: no setpoint {stale[0] - 1} came for state {stale[0]}; "
                                           f"the loop moved on without it (at state {seq})"))

    def _shadow(self, meas, applied: AppliedControl, est) -> None:
        """The candidate predicts beside the active network, on its own inputs."""
        net = self.candidate[0]
        if self._shadow_features is None:
            self._shadow_features = FeatureBuilder(net.feature_set, net.thrust_lag, self.config.dt_s)
            z = self._shadow_features.reset(meas, applied.thrust_n)
        else:
            z = self._shadow_features.build(meas, applied.thrust_n)
        self.shadow.add(net.predict(z)[0], est.f_hat[2])
        active = self.estimator.network
        self.active_shadow.add(active.predict(est.z)[0] if active is not None else 0.0, est.f_hat[2])


def bound_phys(net: LipschitzMLP) -> float:
    return net.lipschitz_bound_physical()


def _predicted_text(predicted: dict | None) -> str:
    from sim.counterfactual import prediction_text

    if not predicted or "change" not in predicted:
        return ""
    return f"; on the recorded flight {prediction_text(predicted)}"


def _describe(net: LipschitzMLP | None, source: str, path: str, net_id: str | None = None) -> dict:
    """A network as NetworkMsg shows it: id, where it came from, inputs, bound and certificate in both units."""
    if net is None:
        return {"id": "none", "source": "none", "path": ""}
    return {"id": net_id or net.metadata.get("id", "unnamed"), "source": source, "path": path,
            "vehicle": net.metadata.get("vehicle", ""), "parent": net.metadata.get("parent", ""),
            "feature_set": net.feature_set.key, "bound_units": net.bound_units,
            "lipschitz_norm": net.certified_lipschitz_normalised(), "lipschitz_phys": net.certified_lipschitz_physical(),
            "certified_phys": net.certified_lipschitz_physical(), "certified_state": net.certified_lipschitz_state(),
            "val_loss": net.metadata.get("val_loss", ""),
            **net.learned}



def shipped(path: str) -> str:
    """``path`` as given when it exists (relative to where neso runs) or when the project ships no file there;
    else the shipped file (``networks/base.safetensors`` from any folder): an absolute path."""
    given = Path(path)
    if given.is_absolute() or given.exists() or not (PROJECT_ROOT / given).is_file():
        return path
    return str(PROJECT_ROOT / given)


def load_flown_network(path: str) -> tuple[LipschitzMLP | None, str]:
    """The network at ``path`` (``""``: none; :func:`shipped` finds the project's own from any folder),
    validated through the file gate; and the path it was read from."""
    if not path:
        return None, "none"
    path = shipped(path)
    return load_network(path, expected_outputs=1), path


def network_certificate(net: LipschitzMLP | None, kp: float, kd: float, omega_o: float, plant: LoopPlant, *,
                        bound: float | None = None) -> FlightCertificate:
    """The one verdict on flying ``net`` (None: no network) with z gains ``kp`` (1/s²), ``kd`` (1/s), ``omega_o``
    (rad/s) on ``plant``, its state slope raised to an operator's L_N ``bound`` when that is higher: what the
    estimator's start, its gate and promotions, and the trainer all ask (:func:`neso.certificate.flight_certificate`)."""
    slopes = NetworkSlopes.of(net) if net is not None else NetworkSlopes(0.0)
    if bound is not None and bound > slopes.state:
        slopes = replace(slopes, state=float(bound))
    return flight_certificate(slopes, kp=kp, kd=kd, omega_o=omega_o, plant=plant)


def startup_network(config: EstimatorConfig, network: LipschitzMLP | None, core_gains: tuple[float, float]
                    ) -> tuple[LipschitzMLP | None, tuple[str, str] | None]:
    """The network to fly at start-up and an event about it: one whose certificate fails is not flown
    unless ``allow_uncertified``."""
    if network is None:
        return None, None
    plant = LoopPlant.of(ControlConfig(vehicle=VehicleModel(mass_kg=config.mass_kg)))
    cert = network_certificate(network, core_gains[0], core_gains[1], config.omega_o_rps, plant)
    if cert.holds:
        return network, ("info", f"network {config.network}: {cert.text()}")
    if config.allow_uncertified:
        return network, ("warning", f"network {config.network} flies OUTSIDE the certificate (--allow-uncertified): "
                                    f"{cert.text()}")
    return None, ("error", f"network {config.network} NOT flown: {cert.text()}; the observer flies alone "
                           "(start with --allow-uncertified to fly it anyway)")
