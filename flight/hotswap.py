"""Hot swap of the predictive network in flight: the candidate gate, the shadow error, the swap.

Pure: no files, no bus. The estimator service reads a candidate's bytes and asks :func:`gate`;
a passed candidate predicts beside the active network (:class:`ShadowError`). The swap itself is
:meth:`neso.estimator.NeuralESO.set_network`: the observer's extended state absorbs the prior's
step, ``x̂3 ← x̂3 + (f_N,old − f_N,new)``, so ``f̂ = f_N + Δf̂`` is the same just before and after.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from neso.netfile import NetworkFileError, network_from_bytes
from neso.network import LipschitzMLP
from runtime.options import option

CERT_RTOL = 1e-6


@dataclass(frozen=True)
class GateVerdict:
    """``network`` is set when the candidate passed; ``reason`` says why not otherwise.
    ``findings``: what the gate measured (str → str), shown to the operator either way."""

    network: LipschitzMLP | None
    reason: str
    findings: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return self.network is not None


def gate(data: bytes, *, active: LipschitzMLP | None, vehicle: str) -> GateVerdict:
    """Check a candidate network file's bytes before it may fly beside ``active`` on ``vehicle``.

    Refused, with the reason: unreadable or truncated, non-finite, inputs (a feature set) this
    version cannot build, hidden and output layers that are not the active network's (the inputs
    may differ: the estimator builds each network's own), an exact SVD certificate over its stated
    bound (checked in physical units, the unit the small-gain condition uses), no validation
    loss in its metadata, or metadata naming another vehicle. Whether its stability certificate
    holds for the gains flown is the estimator's check at the promotion.
    """
    findings: dict[str, str] = {}
    try:
        net = network_from_bytes(data, expected_outputs=1)
    except NetworkFileError as exc:
        return GateVerdict(None, f"network file refused: {exc}", findings)
    findings["layers"] = "→".join(str(n) for n in net.layer_sizes)
    findings["feature_set"] = net.feature_set.key
    if active is not None and net.layer_sizes[1:] != active.layer_sizes[1:]:
        return GateVerdict(None, f"wrong layer shapes: candidate {findings['layers']}, active "
                                 f"{'→'.join(str(n) for n in active.layer_sizes)} (hidden and output layers must match)",
                           findings)
    cert_phys, bound_phys = net.certified_lipschitz_state(), net.lipschitz_bound_physical()
    findings["certified_lipschitz_physical"] = f"{cert_phys:.6g}"
    findings["lipschitz_bound_physical"] = f"{bound_phys:.6g}"
    if not cert_phys <= bound_phys * (1 + CERT_RTOL):
        return GateVerdict(None, f"certificate over its bound: certified {cert_phys:.6g} > bound {bound_phys:.6g} "
                                 "(m/s²)/unit z", findings)
    val = net.metadata.get("val_loss", "")
    try:
        val_loss = float(val)
    except ValueError:
        return GateVerdict(None, f"no validation loss reported (val_loss={val!r})", findings)
    if not math.isfinite(val_loss) or val_loss < 0:
        return GateVerdict(None, f"validation loss {val!r} is not a finite non-negative number", findings)
    findings["val_loss"] = f"{val_loss:.6g}"
    owner = net.metadata.get("vehicle", "")
    if owner != vehicle:
        return GateVerdict(None, f"candidate is for vehicle {owner!r}, this estimator flies {vehicle!r}", findings)
    return GateVerdict(net, "", findings)


class ShadowError:
    """RMS of (candidate's f_N − flown f̂) on the z axis over the last ``window`` samples, m/s²."""

    def __init__(self, window: int = 250) -> None:
        self._sq: deque[float] = deque(maxlen=window)

    def add(self, predicted_mps2: float, f_hat_mps2: float) -> None:
        err = float(predicted_mps2) - float(f_hat_mps2)
        self._sq.append(err * err)

    @property
    def samples(self) -> int:
        return len(self._sq)

    def rms(self) -> float:
        """−1 before the first sample (the NetworkMsg convention for "none")."""
        if not self._sq:
            return -1.0
        return math.sqrt(sum(self._sq) / len(self._sq))


# -- the canary -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CanaryConfig:
    """How the canary judges a promoted network (see :class:`Canary`).

    ``window_samples``: comparable samples after a promotion that decide (500 = 10 s at 50 Hz);
    ``margin``: roll back when the RMS after exceeds the RMS before by more than this fraction *and* by
    more than the noise floor; ``confidence_z``: the floor's one-sided z (2.33: 1 %); ``blocks``: how
    many blocks the window before is cut into to measure that floor; ``min_rms_m``: a floor under the
    RMS before (m), so a millimetre of noise never reads as "twice as bad"; ``trip_samples`` and
    ``trip_factor``: the tripwire, an immediate rollback when the RMS over the last ``trip_samples``
    exceeds ``trip_factor`` times the RMS before.
    """

    window_samples: int = option(500, flag="--canary-window", unit="samples",
                                 help="samples after a promotion that decide the canary")
    margin: float = option(0.10, flag="--canary-margin",
                           help="roll back when tracking is worse by more than this fraction")
    confidence_z: float = 2.33
    blocks: int = 5
    min_rms_m: float = 0.002
    trip_samples: int = 50
    trip_factor: float = 3.0

    def __post_init__(self) -> None:
        if (self.window_samples < 10 or not (0.0 <= self.margin <= 10.0) or self.min_rms_m < 0 or self.blocks < 2
                or self.trip_samples < 5 or self.trip_factor <= 1.0 or self.confidence_z < 0):
            raise ValueError("canary: window_samples >= 10, margin in [0, 10], min_rms_m >= 0, blocks >= 2, "
                             "trip_samples >= 5, trip_factor > 1, confidence_z >= 0")


@dataclass(frozen=True)
class CanaryVerdict:
    """What the canary decided: ``rollback`` true when the network made tracking worse.
    ``threshold``: the ratio it had to exceed (1 + margin, or the noise floor if larger);
    ``tripwire``: decided early on a gross degradation, ``since`` samples after the promotion (the first it may
    is ``trip_samples``: a network that degrades faster is already past the tripwire there)."""

    rollback: bool
    segment: str
    rms_before_m: float
    rms_after_m: float
    samples: int
    threshold: float = 1.0
    tripwire: bool = False
    since: int = 0

    @property
    def change(self) -> float:
        return self.rms_after_m / self.rms_before_m - 1.0 if self.rms_before_m > 0 else math.inf

    def text(self, seq: int | None = None) -> str:
        """In words; ``seq``: the sample it was decided at, named when given."""
        verb = "worse: rolled back" if self.rollback else "kept"
        how = (f"tripwire (> {self.threshold:.1f}× over {self.samples} samples, {self.since} after it)" if self.tripwire else
               f"over {self.samples} samples, threshold {(self.threshold - 1) * 100:+.0f} %")
        at = "" if seq is None else f" at sample {seq}"
        return (f"canary on segment {self.segment!r}{at}: z RMS {self.rms_before_m * 100:.2f} cm before → "
                f"{self.rms_after_m * 100:.2f} cm after the promotion ({self.change * 100:+.0f} %, {how}), {verb}")


def _rms(values) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values)) if values else 0.0


class Canary:
    """Compares the tracking error after a promotion with the error before it on the same mission segment.

    Feed every sample's z tracking error with :meth:`observe` (``segment``: the mission segment the
    reference belongs to; ``run``: a number that changes whenever a new run of a segment begins). An
    :meth:`arm` at the promotion freezes what came before. After it, each sample of a segment is
    paired with the sample at the same offset into that segment's most recent run before the
    promotion (the same place on the same path); where that run has no such sample (a segment still
    running at the promotion), with the last ``window`` samples of it before the promotion. Pairs from
    several segments share one window. When ``window`` pairs have come, the verdict is final: roll back
    if the RMS after exceeds the RMS before by more than ``margin`` and by more than the noise floor —
    how much two windows of the same flight differ by chance, measured on the window before (the
    spread of its blocks' log-RMS, scaled to a window and to a ratio of two, times ``confidence_z``).
    Measured at hover in the simulator: an equal network is rolled back in 5 % of 10 s windows, one with
    80 % more error caught in 84 % (docs/tdr.md "The canary"). Before that, the tripwire rolls back at once a
    network that makes the error grow several-fold (at hover the RMS of 1 s never exceeded 2.6 times that of
    the 10 s before it in 400 s of a good network's flight). Once decided, the canary is disarmed.
    """

    def __init__(self, config: CanaryConfig = CanaryConfig()) -> None:
        self.config = config
        self._runs: dict[str, tuple[int, list[float]]] = {}  # segment → (run number, errors by offset)
        self._frozen: dict[str, tuple[int, list[float]]] | None = None
        self._armed_run: tuple[str, int, int] | None = None  # segment, run, offset at the promotion
        self._trip_before = 0.0
        self._before: list[float] = []
        self._after: list[float] = []
        self._compared: list[str] = []
        self._segment = ""

    @property
    def armed(self) -> bool:
        return self._frozen is not None

    def arm(self) -> None:
        """A promotion just happened: freeze the runs before it."""
        self._frozen = {s: (r, list(e)) for s, (r, e) in self._runs.items()}
        self._armed_run = None
        self._trip_before = 0.0
        if self._segment in self._runs:
            run, errors = self._runs[self._segment]
            self._armed_run = (self._segment, run, len(errors))
            self._trip_before = _rms(errors[-self.config.window_samples:])
        self._before, self._after, self._compared = [], [], []

    def disarm(self) -> None:
        self._frozen = None
        self._before, self._after, self._compared = [], [], []

    def observe(self, segment: str, run: int, error_m: float) -> CanaryVerdict | None:
        """One sample's z error (m); a verdict when one is due, else None."""
        current = self._runs.get(segment)
        if current is None or current[0] != run:
            current = (run, [])
            self._runs[segment] = current
        offset = len(current[1])
        current[1].append(float(error_m))
        self._segment = segment
        if self._frozen is None:
            return None
        trip = self._tripwire(segment, float(error_m))
        if trip is not None:
            return trip
        reference = self._reference(segment, run, offset)
        if reference is None:
            return None
        self._before.append(reference)
        self._after.append(float(error_m))
        if segment not in self._compared:
            self._compared.append(segment)
        if len(self._after) < self.config.window_samples:
            return None
        before = max(_rms(self._before), self.config.min_rms_m)
        after = _rms(self._after)
        threshold = max(1.0 + self.config.margin, self._noise_floor())
        verdict = CanaryVerdict(after > before * threshold, "+".join(self._compared), before, after, len(self._after),
                                threshold)
        self.disarm()
        return verdict

    def _tripwire(self, segment: str, error_m: float) -> CanaryVerdict | None:
        c = self.config
        recent = self._runs[segment][1][-c.trip_samples:]
        since = self._since_promotion(segment)
        if since < c.trip_samples or self._trip_before <= 0:
            return None
        before = max(self._trip_before, c.min_rms_m)
        now = _rms(recent)
        if now <= c.trip_factor * before:
            return None
        verdict = CanaryVerdict(True, segment, before, now, c.trip_samples, c.trip_factor, tripwire=True, since=since)
        self.disarm()
        return verdict

    def _since_promotion(self, segment: str) -> int:
        run, errors = self._runs[segment]
        if self._armed_run is not None and self._armed_run[:2] == (segment, run):
            return len(errors) - self._armed_run[2]
        return len(errors)

    def _noise_floor(self) -> float:
        """The ratio two windows of the flight before differ by at the configured confidence."""
        blocks = [b for b in _split(self._before, self.config.blocks) if b]
        rms = [max(_rms(b), 1e-12) for b in blocks]
        if len(rms) < 2:
            return 1.0
        logs = [math.log(r) for r in rms]
        mean = sum(logs) / len(logs)
        spread = math.sqrt(sum((v - mean) ** 2 for v in logs) / (len(logs) - 1))
        return math.exp(self.config.confidence_z * math.sqrt(2.0) * spread / math.sqrt(len(rms)))

    def _reference(self, segment: str, run: int, offset: int) -> float | None:
        frozen = self._frozen.get(segment)
        if frozen is None:
            return None
        _frozen_run, errors = frozen
        if self._armed_run is not None and self._armed_run[:2] == (segment, run):
            # the run the promotion happened in: compare with its last samples before the promotion
            promoted_at = self._armed_run[2]
            window = errors[max(0, promoted_at - self.config.window_samples):promoted_at]
            if not window:
                return None
            return window[(offset - promoted_at) % len(window)]
        if offset < len(errors):
            return errors[offset]
        return None


def _split(values: list[float], n: int) -> list[list[float]]:
    size = max(1, len(values) // n)
    return [values[i * size:(i + 1) * size] for i in range(n)]
