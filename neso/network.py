"""Lipschitz-bounded ReLU MLP ``h(z)``: the Neural-ESO predictive pathway, pure numpy.

Units. The network is trained on z-scored inputs and labels. ``predict`` takes and returns
physical units (whatever the training data used: m, m/s, N, rad in; m/s^2 out for the paper's
disturbance label); internally ``zn = (z - input_mean) / input_std``, ``y = output_mean +
output_std * h_n(zn)``. The Lipschitz bound ``L_N`` the network was trained to is stated in
*normalised* units (the paper's ``||h||_Lip <= L_N``); the physical constant is
``L_N * max(output_std) / min(input_std)`` (output unit per input unit, mixed SI), which is what
the small-gain condition needs (DESIGN.md "Lipschitz units").

No torch here: this module runs in the control loop.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _readonly_f64(a, name: str, ndim: int) -> np.ndarray:
    arr = np.array(a, dtype=np.float64, copy=True)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    arr.setflags(write=False)
    return arr


def spectral_norms(weights) -> tuple[float, ...]:
    """Exact largest singular value of each weight matrix (SVD)."""
    return tuple(float(np.linalg.norm(w, ord=2)) for w in weights)


@dataclass(frozen=True, eq=False)
class LipschitzMLP:
    """ReLU MLP ``Linear -> ReLU -> ... -> Linear`` with z-score normalisation at both ends.

    ``weights[i]`` has shape ``(n_out_i, n_in_i)`` (torch ``nn.Linear`` layout), ``biases[i]``
    shape ``(n_out_i,)``. ``input_mean``/``input_std`` shape ``(n_in,)``, ``output_mean``/
    ``output_std`` shape ``(n_out,)``, physical units. ``lipschitz_bound`` is ``L_N`` in
    normalised units. Arrays are copied to read-only float64 on construction; shapes are checked.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    input_mean: np.ndarray
    input_std: np.ndarray
    output_mean: np.ndarray
    output_std: np.ndarray
    lipschitz_bound: float
    metadata: dict[str, str] = field(default_factory=dict)
    # Folded parameters for predict(): normalisation absorbed into the first/last layer.
    _fw: tuple[np.ndarray, ...] = field(init=False, repr=False)
    _fb: tuple[np.ndarray, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        ws = tuple(_readonly_f64(w, f"weights[{i}]", 2) for i, w in enumerate(self.weights))
        bs = tuple(_readonly_f64(b, f"biases[{i}]", 1) for i, b in enumerate(self.biases))
        if not ws:
            raise ValueError("network needs at least one layer")
        if len(ws) != len(bs):
            raise ValueError(f"{len(ws)} weight matrices but {len(bs)} bias vectors")
        for i, (w, b) in enumerate(zip(ws, bs)):
            if b.shape[0] != w.shape[0]:
                raise ValueError(f"bias {i} has length {b.shape[0]}, layer {i} has {w.shape[0]} outputs")
            if i > 0 and w.shape[1] != ws[i - 1].shape[0]:
                raise ValueError(
                    f"layer chain inconsistent: layer {i} takes {w.shape[1]} inputs, "
                    f"layer {i - 1} gives {ws[i - 1].shape[0]}")
        n_in, n_out = ws[0].shape[1], ws[-1].shape[0]
        im = _readonly_f64(self.input_mean, "input_mean", 1)
        isd = _readonly_f64(self.input_std, "input_std", 1)
        om = _readonly_f64(self.output_mean, "output_mean", 1)
        osd = _readonly_f64(self.output_std, "output_std", 1)
        for name, v, n in (("input_mean", im, n_in), ("input_std", isd, n_in),
                           ("output_mean", om, n_out), ("output_std", osd, n_out)):
            if v.shape[0] != n:
                raise ValueError(f"{name} has length {v.shape[0]}, network expects {n}")
        if np.any(isd <= 0) or np.any(osd <= 0):
            raise ValueError("normalisation std must be > 0")
        arrays = (*ws, *bs, im, isd, om, osd)
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise ValueError("network parameters must be finite (NaN or inf found)")
        bound = float(self.lipschitz_bound)
        if not (np.isfinite(bound) and bound > 0):
            raise ValueError(f"lipschitz_bound must be finite and > 0, got {bound}")
        meta = {str(k): str(v) for k, v in dict(self.metadata).items()}

        # Fold the z-scores: W0' = W0 / std_in, b0' = b0 - W0' mean_in; last layer times std_out.
        fw = [w.copy() for w in ws]
        fb = [b.copy() for b in bs]
        fw[0] = fw[0] / isd[None, :]
        fb[0] = fb[0] - fw[0] @ im
        fw[-1] = fw[-1] * osd[:, None]
        fb[-1] = fb[-1] * osd + om
        for a in (*fw, *fb):
            a.setflags(write=False)

        for name, value in (("weights", ws), ("biases", bs), ("input_mean", im), ("input_std", isd),
                            ("output_mean", om), ("output_std", osd), ("lipschitz_bound", bound),
                            ("metadata", meta), ("_fw", tuple(fw)), ("_fb", tuple(fb))):
            object.__setattr__(self, name, value)

    # ---- shape helpers -------------------------------------------------------------------
    @property
    def n_inputs(self) -> int:
        return int(self.weights[0].shape[1])

    @property
    def n_outputs(self) -> int:
        return int(self.weights[-1].shape[0])

    @property
    def n_layers(self) -> int:
        return len(self.weights)

    @property
    def layer_sizes(self) -> tuple[int, ...]:
        """``(n_in, hidden..., n_out)``, e.g. ``(5, 20, 25, 10, 1)``."""
        return (self.n_inputs, *(int(w.shape[0]) for w in self.weights))

    # ---- evaluation ----------------------------------------------------------------------
    def predict(self, z: np.ndarray) -> np.ndarray:
        """Physical-unit prediction. ``z`` shape ``(n_in,)`` -> ``(n_out,)``; ``(N, n_in)`` -> ``(N, n_out)``."""
        fw, fb = self._fw, self._fb
        last = len(fw) - 1
        x = np.asarray(z, dtype=np.float64)
        if x.ndim == 1:
            for i in range(last):
                x = fw[i] @ x
                x += fb[i]
                np.maximum(x, 0.0, out=x)
            x = fw[last] @ x
            x += fb[last]
            return x
        if x.ndim != 2:
            raise ValueError(f"z must have shape (n_in,) or (N, n_in), got {x.shape}")
        for i in range(last):
            x = x @ fw[i].T
            x += fb[i]
            np.maximum(x, 0.0, out=x)
        x = x @ fw[last].T
        x += fb[last]
        return x

    def predict_normalised(self, zn: np.ndarray) -> np.ndarray:
        """``h_n`` on z-scored inputs, z-scored output. Shapes as ``predict``."""
        x = np.asarray(zn, dtype=np.float64)
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = x @ w.T + b
            if i < len(self.weights) - 1:
                x = np.maximum(x, 0.0)
        return x

    # ---- certificates --------------------------------------------------------------------
    def certified_lipschitz_normalised(self) -> float:
        """Upper bound on ``||h_n||_Lip`` (z-scored in and out, 2-norms): the exact product of
        each layer's largest singular value (ReLU is 1-Lipschitz). Dimensionless."""
        return float(np.prod(spectral_norms(self.weights)))

    def certified_lipschitz_physical(self) -> float:
        """``certified_lipschitz_normalised() * max(output_std) / min(input_std)``: a bound on the
        physical map's Lipschitz constant in (output unit) per (input unit), with the input
        components mixing SI units (m, m/s, N, rad) as they come."""
        return self.certified_lipschitz_normalised() * float(np.max(self.output_std)) / float(np.min(self.input_std))

    def lipschitz_bound_physical(self) -> float:
        """The stated bound ``L_N`` converted to physical units as above."""
        return self.lipschitz_bound * float(np.max(self.output_std)) / float(np.min(self.input_std))

    def scaled_to_bound(self, bound: float) -> LipschitzMLP:
        """A copy whose certificate is ``<= bound``, with ``lipschitz_bound = bound``.

        If the certificate ``C`` exceeds ``bound``, each weight is multiplied by
        ``c = (bound / C)^(1/n)`` and bias ``i`` (0-based) by ``c^(i+1)``. Since ReLU is positively
        homogeneous, the normalised map becomes exactly ``c^n * h_n`` (same shape, flatter slope).
        A hair of extra shrink absorbs float rounding in the SVD product. Otherwise the weights
        are copied unchanged.
        """
        bound = float(bound)
        cert = self.certified_lipschitz_normalised()
        ws, bs = list(self.weights), list(self.biases)
        if cert > bound:
            n = len(ws)
            c = (bound / cert) ** (1.0 / n)
            ws = [w * c for w in ws]
            bs = [b * c ** (i + 1) for i, b in enumerate(bs)]
            new_cert = float(np.prod(spectral_norms(ws)))
            if new_cert > bound:  # rounding: shrink the last layer only, by a relative ~1e-15
                f = bound / new_cert * (1.0 - 1e-12)
                ws[-1] = ws[-1] * f
                bs[-1] = bs[-1] * f
        return LipschitzMLP(tuple(ws), tuple(bs), self.input_mean, self.input_std,
                            self.output_mean, self.output_std, bound, dict(self.metadata))
