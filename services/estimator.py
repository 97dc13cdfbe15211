"""``estimator``: Neural-ESO on the bus, with live pathway and Lipschitz bound.

The step object (:class:`EstimatorCore`) runs :class:`neso.estimator.NeuralESO` on each state
sample with the control that acted over the period before it (the setpoint answering the
previous sample; in lockstep it waits for that setpoint, in real time it takes the newest).
Live parameters:

- ``pathway`` (``neural_eso``, ``eso``, ``nn``, ``none``): switched bumplessly at the next sample.
- ``lipschitz_bound`` (L_N, normalised units as the paper trains): the network trained for that
  bound if one is in the network directory (same training data as the loaded one), otherwise
  the loaded network with its layers scaled down until its exact certificate meets the bound.
  A bound above the one the loaded network was trained to, with no network for it on disk, is
  refused: scaling can only flatten a network. The broadcast says which was done.
- ``omega_o_rps``: shown so watchers (the dashboard's certificate) know the observer bandwidth;
  read-only (its range is the start-up value), since it is start-up config (``--omega-o``).

Network hot swap (commands on ``neso/<v>/cmd/estimator``; each replies ok=False with the reason
when refused, and a refusal leaves the active network flying):

- ``offer {path}``: a candidate network file (normally from the registry) goes through the gate
  (:func:`neso.hotswap.gate`: readable, finite, same layer shapes, certificate within its bound
  in physical units, validation loss present, trained for this vehicle). A passed one runs in
  **shadow**: it predicts beside the active network every sample, and its RMS error against
  the flown f̂ (z axis, last 5 s) is in ``NetworkMsg.shadow_error_rms_mps2``; the active
  network's own error over the same samples is ``candidate["active_error_rms_mps2"]``.
- ``promote``: the candidate becomes the active network at the next sample; Δf̂ absorbs the
  step so f̂ is continuous (:meth:`neso.estimator.NeuralESO.set_network`). The active one becomes ``previous``.
- ``rollback``: the previous network flies again, the same bumpless way.
- ``reject``: drop the candidate.

A retried command is done once: ``runtime.client.command`` sends a request id and the node
answers a repeat with the first answer (:class:`runtime.node.AnsweredOnce`), so a second
rollback never undoes the first.

``NetworkMsg`` on ``neso/<v>/network``: once a second and on every change.
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neso.control import PositionController, ControlConfig
from neso.eso import EsoConfig
from neso.estimator import PATHWAYS, AppliedControl, NeuralESO, NeuralEsoConfig
from neso.features import N_FEATURES
from neso.hotswap import GateVerdict, ShadowError, gate
from neso.netfile import NetworkFileError, load_network
from neso.network import LipschitzMLP
from runtime.params import Param
from runtime.schema import EstimateMsg, NetworkMsg, SetpointMsg, StateMsg, state_measurement, vec

DEFAULT_NETWORK = "networks/base-L1.safetensors"
_KEEP = 64
SHADOW_WINDOW = 250  # samples: 5 s at 50 Hz
MAX_NETWORK_FILE_BYTES = 10_000_000


@dataclass(frozen=True)
class EstimatorConfig:
    """``network``: the network file flown (``""``: none; nn/neural_eso then predict 0).
    ``network_dir``: where networks trained for other bounds are looked for."""

    network: str = DEFAULT_NETWORK
    network_dir: str = "networks"
    pathway: str = "neural_eso"
    omega_o_rps: float = 15.0
    dt_s: float = 0.02
    lockstep: bool = False


def estimator_params(config: EstimatorConfig, bound: float) -> tuple[Param, ...]:
    return (
        Param("pathway", config.pathway, str, "which pathways make f̂", choices=PATHWAYS),
        Param("lipschitz_bound", bound, float, "L_N of the network flown (normalised units)", lo=1e-6, hi=1e3),
        Param("omega_o_rps", config.omega_o_rps, float, "observer bandwidth (start-up config: read-only)", "rad/s",
              lo=config.omega_o_rps, hi=config.omega_o_rps),
    )


def _same_bound(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9)


class NetworkChoice:
    """Which network flies at a given L_N: one trained for it on disk, or the loaded one scaled."""

    def __init__(self, loaded: LipschitzMLP | None, source: str, directory: str | None) -> None:
        self.loaded, self.source = loaded, source
        self.trained: dict[float, tuple[LipschitzMLP, str]] = {}
        self.skipped: list[str] = []
        if loaded is None or not directory or not Path(directory).is_dir():
            return
        family = loaded.metadata.get("training_data", "")
        for path in sorted(Path(directory).glob("*.safetensors")):
            try:
                net = load_network(path, expected_inputs=N_FEATURES, expected_outputs=loaded.n_outputs)
            except NetworkFileError as exc:
                self.skipped.append(f"{path}: {exc}")
                continue
            if net.metadata.get("training_data", "") == family:
                self.trained.setdefault(net.lipschitz_bound, (net, str(path)))

    def refusal(self, bound: float) -> str | None:
        if self.loaded is None:
            return "no network is loaded, so there is no L_N to set"
        if any(_same_bound(bound, b) for b in self.trained) or bound <= self.loaded.lipschitz_bound * (1 + 1e-9):
            return None
        return (f"L_N={bound:g} is above the {self.loaded.lipschitz_bound:g} the loaded network was trained to, and no "
                f"network trained for {bound:g} on the same data is on disk (have: {sorted(self.trained)})")

    def network_for(self, bound: float) -> tuple[LipschitzMLP, str]:
        """(network, what was done) for L_N = ``bound`` (call only if :meth:`refusal` is None)."""
        for b, (net, path) in self.trained.items():
            if _same_bound(b, bound):
                return net, f"loaded {path}, trained for L_N={b:g} (certified {net.certified_lipschitz_normalised():.4g} " \
                            f"normalised, {net.certified_lipschitz_physical():.4g} physical)"
        net = self.loaded.scaled_to_bound(bound)
        return net, (f"no network trained for L_N={bound:g} on disk: scaled {self.source} (trained for "
                     f"{self.loaded.lipschitz_bound:g}) down to certified {net.certified_lipschitz_normalised():.4g} "
                     f"normalised, {net.certified_lipschitz_physical():.4g} physical")


class EstimatorCore:
    """The pure step object: :meth:`on_setpoint` and :meth:`on_state` return the estimates to publish."""

    def __init__(self, config: EstimatorConfig, network: LipschitzMLP | None, choice: NetworkChoice,
                 vehicle: str = "uav1") -> None:
        self.config = config
        self.choice = choice
        self.vehicle = vehicle
        self.network_id = network.metadata.get("id", "unnamed") if network is not None else "none"
        self.active_info = _describe(network, "file", choice.source)
        self.candidate: tuple[LipschitzMLP, dict] | None = None
        self.previous: tuple[LipschitzMLP | None, dict] | None = None
        self.shadow = ShadowError(SHADOW_WINDOW)
        self.active_shadow = ShadowError(SHADOW_WINDOW)  # the active network's error, same samples
        self.swapped = False  # a network from an offer is flying (the L_N parameter no longer picks networks)
        self.changes = 0  # bumped on every network change, so the adapter publishes NetworkMsg at once
        self.estimator = NeuralESO(NeuralEsoConfig(eso=EsoConfig(omega_o_rps=config.omega_o_rps, dt_s=config.dt_s),
                                                   pathway=config.pathway), network)
        self._hover = PositionController(ControlConfig(dt_s=config.dt_s)).hover_output().applied
        self._applied: dict[int, AppliedControl] = {}
        self._latest_applied: AppliedControl | None = None
        self._waiting: list[StateMsg] = []
        self._last_seq = -1
        self._last_output: EstimateMsg | None = None
        self.warm_ticks = 0

    # -- live parameters ----------------------------------------------------------------
    def check(self, values: dict) -> str | None:
        bound = values["lipschitz_bound"]
        if self.estimator.network is None or _same_bound(bound, self.estimator.network.lipschitz_bound):
            return None
        if self.swapped:
            return (f"the active network {self.network_id} came from an offer: its L_N "
                    f"{self.estimator.network.lipschitz_bound:g} is fixed (train another, or rollback)")
        return self.choice.refusal(bound)

    def apply(self, changed: dict) -> str:
        notes = []
        if "pathway" in changed:
            self.estimator.set_pathway(changed["pathway"])
            notes.append(f"pathway {changed['pathway']}")
        if "lipschitz_bound" in changed and self.choice.loaded is not None and not self.swapped:
            net, note = self.choice.network_for(changed["lipschitz_bound"])
            self.estimator.set_network(net)
            self.network_id = f"{net.metadata.get('id', 'unnamed')}@L{changed['lipschitz_bound']:g}"
            path = next((p for n, p in self.choice.trained.values() if n is net), None)
            self.active_info = _describe(net, "scaled" if path is None else "file", path or self.choice.source,
                                         self.network_id)
            self.changes += 1
            notes.append(note)
        return "; ".join(notes)

    # -- network hot swap ---------------------------------------------------------------
    def check_offer(self, path: str) -> GateVerdict:
        """Read and gate a candidate file (touches no estimator state but the active network)."""
        try:
            size = Path(path).stat().st_size
            if size > MAX_NETWORK_FILE_BYTES:
                return GateVerdict(None, f"network file {path} is {size} bytes (> {MAX_NETWORK_FILE_BYTES})")
            data = Path(path).read_bytes()
        except OSError as exc:
            return GateVerdict(None, f"cannot read {path}: {exc.strerror or exc}")
        return gate(data, active=self.estimator.network, vehicle=self.vehicle)

    def accept(self, verdict: GateVerdict, path: str) -> str:
        """Put a passed candidate in shadow (replacing any earlier candidate)."""
        net = verdict.network
        info = _describe(net, "registry", path)
        info.update(state="shadow", **{k: v for k, v in verdict.findings.items() if k not in info})
        self.candidate = (net, info)
        self.shadow = ShadowError(SHADOW_WINDOW)
        self.active_shadow = ShadowError(SHADOW_WINDOW)
        self.changes += 1
        return f"candidate {info['id']} in shadow ({verdict.findings.get('layers')}, val_loss {info['val_loss']})"

    def promote(self) -> tuple[bool, str]:
        if self.candidate is None:
            return False, "no candidate to promote (offer one first)"
        net, info = self.candidate
        shadow = self.shadow.rms()
        self.previous = (self.estimator.network, self.active_info)
        self.estimator.set_network(net)
        info = {k: v for k, v in info.items() if k != "state"}
        self.active_info, self.network_id, self.candidate, self.swapped = info, info["id"], None, True
        self.changes += 1
        return True, f"promoted {info['id']} (shadow error {shadow:.4g} m/s²); previous {self.previous[1]['id']}"

    def rollback(self) -> tuple[bool, str]:
        if self.previous is None:
            return False, "no previous network to roll back to"
        net, info = self.previous
        self.previous = (self.estimator.network, self.active_info)
        self.estimator.set_network(net)
        self.active_info, self.network_id = info, info["id"]
        self.swapped = info.get("source") == "registry"
        self.changes += 1
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
        return NetworkMsg(stamp_s=time.monotonic(), seq=max(self._last_seq, 0), active=self.active_info,
                          candidate=candidate,
                          previous=self.previous[1] if self.previous is not None else {},
                          shadow_error_rms_mps2=self.shadow.rms() if self.candidate is not None else -1.0)

    # -- samples ------------------------------------------------------------------------
    def on_setpoint(self, sp: SetpointMsg, now_s: float) -> list[EstimateMsg]:
        applied = AppliedControl(acc_cmd_enu_mps2=np.array(sp.acc_cmd_enu_mps2), thrust_n=sp.thrust_n)
        self._applied[sp.seq] = applied
        self._latest_applied = applied
        for old in [s for s in self._applied if s < sp.seq - _KEEP]:
            del self._applied[old]
        out = []
        while self._waiting and self._waiting[0].seq - 1 in self._applied:
            out += self._process(self._waiting.pop(0), now_s)
        return out

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
            self.warm_ticks = 0
        else:
            applied = self._applied.get(state.seq - 1) or self._latest_applied or self._hover
        self._last_seq = state.seq
        est = self.estimator.update(meas, applied)
        self.warm_ticks += 1
        if self.candidate is not None:
            self.shadow.add(self.candidate[0].predict(est.z)[0], est.f_hat[2])
            active = self.estimator.network
            self.active_shadow.add(active.predict(est.z)[0] if active is not None else 0.0, est.f_hat[2])
        self._last_output = EstimateMsg(
            seq=state.seq, stamp_s=time.monotonic(), t_s=state.t_s, f_hat_mps2=vec(est.f_hat), f_n_mps2=vec(est.f_n),
            delta_f_hat_mps2=vec(est.delta_f_hat), z=vec(est.z), pathway=est.pathway, network_id=self.network_id,
            warm_ticks=self.warm_ticks)
        return [self._last_output]


def _describe(net: LipschitzMLP | None, source: str, path: str, net_id: str | None = None) -> dict:
    """A network as NetworkMsg shows it: id, where it came from, bound and certificate in both units."""
    if net is None:
        return {"id": "none", "source": "none", "path": ""}
    return {"id": net_id or net.metadata.get("id", "unnamed"), "source": source, "path": path,
            "vehicle": net.metadata.get("vehicle", ""), "parent": net.metadata.get("parent", ""),
            "lipschitz_norm": net.lipschitz_bound, "lipschitz_phys": net.lipschitz_bound_physical(),
            "certified_phys": net.certified_lipschitz_physical(), "val_loss": net.metadata.get("val_loss", "")}


def load_flown_network(path: str) -> tuple[LipschitzMLP | None, str]:
    """The network at ``path`` (``""``: none), validated through the file gate."""
    if not path:
        return None, "none"
    return load_network(path, expected_inputs=N_FEATURES, expected_outputs=1), path


# -- bus adapter ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--network", default=DEFAULT_NETWORK, help="network file flown ('' for none)")
    parser.add_argument("--network-dir", default="networks", help="networks trained for other L_N")
    parser.add_argument("--pathway", default="neural_eso", choices=PATHWAYS)
    parser.add_argument("--omega-o", type=float, default=15.0, help="observer bandwidth rad/s")
    parser.add_argument("--rate", type=float, default=50.0, help="sample rate Hz (must match the source)")


def config_from_args(args) -> EstimatorConfig:
    return EstimatorConfig(network=args.network, network_dir=args.network_dir, pathway=args.pathway,
                           omega_o_rps=args.omega_o, dt_s=1.0 / args.rate, lockstep=getattr(args, "lockstep", False))


def run(args, bus) -> int:
    from runtime.node import Node, run_node
    from runtime.params import ParamSet

    config = config_from_args(args)
    network, source = load_flown_network(config.network)
    choice = NetworkChoice(network, source, config.network_dir)
    core = EstimatorCore(config, network, choice, vehicle=args.vehicle)
    bound = network.lipschitz_bound if network is not None else 1.0
    params = ParamSet(estimator_params(config, bound), check=core.check)
    node = Node("estimator", vehicle=args.vehicle, bus=bus, config=config, params=params)
    if network is not None:
        node.log(f"network {source}: id {core.network_id}, L_N {network.lipschitz_bound:g} normalised "
                 f"({network.lipschitz_bound_physical():.4g} physical); networks for L_N {sorted(choice.trained)} on disk")
    for skipped in choice.skipped:
        node.log(f"skipped {skipped}")
    put = node.publisher("estimate")

    def publish(estimates: list[EstimateMsg], received_s: float) -> None:
        for est in estimates:
            put(est)
            node.stats.output(time.monotonic() - received_s)

    def on_state(msg: StateMsg, received_s: float) -> None:
        changed = params.take_pending()
        if changed:
            note = core.apply(changed)
            node.broadcast_params(msg.seq, note)
            node.event("info", f"from sample {msg.seq}: {note}")
        publish(core.on_state(msg, received_s), received_s)

    def on_setpoint(msg: SetpointMsg, received_s: float) -> None:
        publish(core.on_setpoint(msg, received_s), received_s)

    put_network = node.publisher("network")
    published_changes = [-1]

    def publish_network() -> None:  # call under the node lock
        put_network(core.network_msg())
        published_changes[0] = core.changes

    def swap_command(name: str, cmd_args: dict) -> tuple[bool, str]:
        if name == "offer":
            path = cmd_args.get("path")
            if not isinstance(path, str) or not path:
                return False, "offer needs args {path: network file}"
            verdict = core.check_offer(path)  # outside the lock: reads a file
            with node.lock:
                if not verdict.passed:
                    node.event("warning", f"candidate {path} refused: {verdict.reason}; active {core.network_id} "
                                          "keeps flying")
                    return False, verdict.reason
                message = core.accept(verdict, path)
                publish_network()
            node.event("info", message)
            return True, message
        actions = {"promote": core.promote, "rollback": core.rollback, "reject": core.reject}
        if name not in actions:
            return False, f"unknown command {name!r}; estimator takes offer, promote, rollback, reject"
        with node.lock:
            ok, message = actions[name]()
            if ok:
                publish_network()
        node.event("info" if ok else "warning", message)
        return ok, message

    def network_loop(n: Node) -> None:
        next_s = time.monotonic()
        while not n.wait(0.05):
            with n.lock:
                if core.changes != published_changes[0] or time.monotonic() >= next_s:
                    publish_network()
                    next_s = time.monotonic() + 1.0

    node.subscribe("state", on_state)
    node.subscribe("setpoint", on_setpoint)
    node.on_command(swap_command, unlocked=("offer", "promote", "rollback", "reject"))
    node.status_hook = lambda: f"ok, pathway {core.estimator.pathway}, network {core.network_id}"
    return run_node(node, network_loop)
