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

    Refused, with the reason: unreadable or truncated, non-finite, a layer chain that is not the
    active network's (``5→…→1`` of the same sizes), an exact SVD certificate over its stated
    bound (checked in physical units, ``L·σ_y/min σ_z``, the unit the small-gain condition
    uses), no validation loss in its metadata, or metadata naming another vehicle.
    """
    findings: dict[str, str] = {}
    try:
        net = network_from_bytes(data, expected_inputs=5, expected_outputs=1)
    except NetworkFileError as exc:
        return GateVerdict(None, f"network file refused: {exc}", findings)
    findings["layers"] = "→".join(str(n) for n in net.layer_sizes)
    if active is not None and net.layer_sizes != active.layer_sizes:
        return GateVerdict(None, f"wrong layer shapes: candidate {findings['layers']}, active "
                                 f"{'→'.join(str(n) for n in active.layer_sizes)}", findings)
    cert_phys, bound_phys = net.certified_lipschitz_physical(), net.lipschitz_bound_physical()
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
