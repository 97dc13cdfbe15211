"""Lipschitz-bounded ReLU MLP ``h(z)``: the Neural-ESO predictive pathway, pure numpy.

Units. The network is trained on z-scored inputs and labels. ``predict`` takes and returns
physical units (m, m/s, N, rad in, as the network's feature set says; m/s² out for the
disturbance label); internally ``zn = (z - input_mean) / input_std``, ``y = output_mean +
output_std * h_n(zn)``.

Two Lipschitz constants, both certified from the weights by exact SVD products (ReLU is
1-Lipschitz):

* *normalised*, ``∏ ‖W_i‖``: the paper's ``||h||_Lip <= L_N`` on the z-scored map;
* *physical*, ``∏ ‖W̃_i‖`` with the z-scores folded into the end layers,
  ``W̃_1 = W_1 diag(1/σ_z)`` and ``W̃_n = diag(σ_y) W_n``: (m/s²) per unit of the mixed-SI
  input (Euclidean norm) (DESIGN.md "Lipschitz units"); restricted to the columns of the axis'
  tracked state (``certified_lipschitz_state``) it is what the small-gain certificate needs.
  It is never above the loose ``L_N·max σ_y/min σ_z``: a roll angle with σ = 0.024 rad no
  longer inflates a bound on an input the network barely uses.

A network states its bound in one of the two (``bound_units``): the paper's networks in
normalised units, this project's default networks in physical units on the state inputs (trained
to the largest bound the certificate allows for the gains flown).

No torch here: this module runs in the control loop.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from neso.features import LEGACY_FEATURE_SET, FeatureSet, FeatureSetError, ThrustLag, feature_set
from neso.learning import equivalent_gains


def _readonly_f64(a, name: str, ndim: int) -> np.ndarray:
    arr = np.array(a, dtype=np.float64, copy=True)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    arr.setflags(write=False)
    return arr


BOUND_UNITS = ("normalised", "physical")


def spectral_norms(weights) -> tuple[float, ...]:
    """Exact largest singular value of each weight matrix (SVD)."""
    return tuple(float(np.linalg.norm(w, ord=2)) for w in weights)


def fold_scalers(weights, input_std: np.ndarray, output_std: np.ndarray) -> list[np.ndarray]:
    """The weight matrices with the z-scores folded in: ``W_1 diag(1/σ_z)`` first, ``diag(σ_y) W_n``
    last (both for a single layer). Biases do not change a Lipschitz constant."""
    ws = [np.asarray(w, dtype=float) for w in weights]
    ws[0] = ws[0] / np.asarray(input_std)[None, :]
    ws[-1] = np.asarray(output_std)[:, None] * ws[-1]
    return ws


@dataclass(frozen=True, eq=False)
class LipschitzMLP:
    """ReLU MLP ``Linear -> ReLU -> ... -> Linear`` with z-score normalisation at both ends.

    ``weights[i]`` has shape ``(n_out_i, n_in_i)`` (torch ``nn.Linear`` layout), ``biases[i]``
    shape ``(n_out_i,)``. ``input_mean``/``input_std`` shape ``(n_in,)``, ``output_mean``/
    ``output_std`` shape ``(n_out,)``, physical units. ``lipschitz_bound`` is the stated bound in
    ``bound_units`` (``normalised``: the paper's ``L_N``; ``physical``: (m/s²) per unit z). Arrays
    are copied to read-only float64 on construction; shapes are checked.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    input_mean: np.ndarray
    input_std: np.ndarray
    output_mean: np.ndarray
    output_std: np.ndarray
    lipschitz_bound: float
    metadata: dict[str, str] = field(default_factory=dict)
    bound_units: str = "normalised"
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
        if self.bound_units not in BOUND_UNITS:
            raise ValueError(f"bound_units must be one of {BOUND_UNITS}, got {self.bound_units!r}")
        meta = {str(k): str(v) for k, v in dict(self.metadata).items()}
        if "feature_set" in meta:
            fs = feature_set(meta["feature_set"])  # FeatureSetError (a ValueError) names the known ones
            if fs.size != n_in:
                raise FeatureSetError(f"feature set {fs.key} has {fs.size} inputs, the network takes {n_in}")
            meta["feature_set"] = fs.key

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
    def feature_set(self) -> FeatureSet:
        """The input vector the network was trained on (metadata ``feature_set``; files written before
        feature sets were recorded were trained on the paper's input)."""
        fs = feature_set(self.metadata.get("feature_set", LEGACY_FEATURE_SET))
        if fs.size != self.n_inputs:
            raise FeatureSetError(f"the network takes {self.n_inputs} inputs and declares no feature set "
                                  f"(the paper's {fs.key} has {fs.size})")
        return fs

    @property
    def thrust_lag(self) -> ThrustLag:
        """The applied-thrust model its ``thrust_applied_n`` input was built with (metadata
        ``thrust_lag_s``, ``thrust_delay_s``; none: no lag)."""
        return ThrustLag(float(self.metadata.get("thrust_lag_s", 0.0)), float(self.metadata.get("thrust_delay_s", 0.0)))

    @property
    def learned(self) -> dict:
        """What training recorded about what it learned, JSON-safe: ``val_loss_vs_mean`` (validation MSE over
        that of predicting the mean; None if not recorded), ``slopes`` (mean physical ∂h/∂input by input name) and
        ``gain_change``: the slopes on p_z and v_z as a change of the z gains (``dkp`` 1/s², ``dkd`` 1/s;
        :func:`neso.learning.equivalent_gains`; None without them)."""

        try:
            slopes = {str(k): float(v) for k, v in json.loads(self.metadata.get("slopes", "{}")).items()}
        except (ValueError, AttributeError):
            slopes = {}
        try:
            vs = float(self.metadata.get("val_loss_vs_mean", "nan"))
        except ValueError:
            vs = float("nan")
        slopes = {k: v for k, v in slopes.items() if np.isfinite(v)}
        change = equivalent_gains(slopes)
        return {"val_loss_vs_mean": vs if np.isfinite(vs) else None, "slopes": slopes,
                "gain_change": None if change is None else change.to_dict()}

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

    def input_gradients(self, z: np.ndarray) -> np.ndarray:
        """Physical slopes ``∂h_j/∂z_i`` at each input (``z`` (N, n_in) → (N, n_out, n_in); output unit per
        input unit), exact for the ReLU network (the right derivative at a kink)."""
        fw, fb = self._fw, self._fb
        x = np.asarray(z, dtype=np.float64)
        if x.ndim != 2:
            raise ValueError(f"z must have shape (N, n_in), got {x.shape}")
        masks = []
        for i in range(len(fw) - 1):
            x = x @ fw[i].T + fb[i]
            masks.append(x > 0.0)
            x = np.maximum(x, 0.0)
        grad = np.broadcast_to(fw[-1], (len(masks[0]) if masks else len(z), *fw[-1].shape)).copy()
        for i in range(len(fw) - 2, -1, -1):
            grad = (grad * masks[i][:, None, :]) @ fw[i]
        return grad

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
        """Upper bound on the physical map's Lipschitz constant, (output unit) per (input unit) with
        the inputs' mixed SI units as they come: the exact SVD product of the folded weights."""
        return float(np.prod(spectral_norms(fold_scalers(self.weights, self.input_std, self.output_std))))

    def certified_lipschitz_columns(self, columns) -> float:
        """Upper bound on the Lipschitz constant in the inputs ``columns`` alone (the others held
        fixed), physical units: the folded first layer restricted to those columns."""
        ws = fold_scalers(self.weights, self.input_std, self.output_std)
        ws[0] = ws[0][:, list(columns)]
        return float(np.prod(spectral_norms(ws)))

    @property
    def state_columns(self) -> tuple[int, ...]:
        """The inputs that are its axis' tracked state (position, velocity): the ones the stability certificate
        counts in the loop gain (:mod:`neso.certificate.roles`); every input if its feature set is unknown."""
        try:
            return self.feature_set.state_columns
        except FeatureSetError:
            return tuple(range(self.n_inputs))

    def role_columns(self) -> dict[str, tuple[int, ...]]:
        """Its inputs by role (:attr:`neso.features.FeatureSet.role_columns`); every input ``state`` if its feature
        set is unknown (the certificate then counts all of them in the loop)."""
        try:
            return self.feature_set.role_columns
        except FeatureSetError:
            return {"state": tuple(range(self.n_inputs)), "thrust": (), "attitude": (), "speed": ()}

    def certified_lipschitz_state(self) -> float:
        """Upper bound on the Lipschitz constant in the state inputs alone, physical units (0 without any):
        what the stability certificate's verdict needs."""
        cols = self.state_columns
        return self.certified_lipschitz_columns(cols) if cols else 0.0

    def certified_lipschitz(self) -> float:
        """The certificate in the network's own ``bound_units``: normalised, the whole z-scored map; physical,
        the state inputs (a physical bound states the loop gain the certificate needs; the other inputs only
        move the ultimate bound, :mod:`neso.certificate.roles`)."""
        if self.bound_units == "physical":
            return self.certified_lipschitz_state()
        return self.certified_lipschitz_normalised()

    def lipschitz_bound_physical(self) -> float:
        """The stated bound in physical units: itself (on the state inputs), or for a normalised bound the
        (loose) ``L_N * max(output_std) / min(input_std)``, which the folded certificate of all the inputs,
        hence of the state inputs, never exceeds."""
        if self.bound_units == "physical":
            return float(self.lipschitz_bound)
        return self.lipschitz_bound * float(np.max(self.output_std)) / float(np.min(self.input_std))

    def with_scalers(self, input_mean, input_std, output_mean, output_std) -> LipschitzMLP:
        """The same function (to rounding) under other z-score statistics: the first and last layers
        absorb the change. The physical certificate is unchanged; the normalised one is not."""
        im, isd = np.asarray(input_mean, float), np.asarray(input_std, float)
        om, osd = np.asarray(output_mean, float), np.asarray(output_std, float)
        ws, bs = [np.array(w) for w in self.weights], [np.array(b) for b in self.biases]
        # first layer: W1 (z - μ)/σ + b1 = W1 diag(σ'/σ) (z - μ')/σ' + b1 + W1 (μ' - μ)/σ
        bs[0] = bs[0] + ws[0] @ ((im - self.input_mean) / self.input_std)
        ws[0] = ws[0] * (isd / self.input_std)[None, :]
        # last layer: μ_y + σ_y (W_n x + b_n) = μ'_y + σ'_y (W'_n x + b'_n)
        ratio = self.output_std / osd
        ws[-1] = ws[-1] * ratio[:, None]
        bs[-1] = bs[-1] * ratio + (self.output_mean - om) / osd
        return LipschitzMLP(tuple(ws), tuple(bs), im, isd, om, osd, self.lipschitz_bound, dict(self.metadata),
                            self.bound_units)

    def within_block_bounds(self, blocks, bounds) -> LipschitzMLP:
        """A copy whose physical certificate in each block of input columns (``blocks``: tuples of indices) is at
        most that block's bound (``bounds``, (m/s²) per unit): the first layer's columns of a block over its bound
        are scaled by ``bound / certificate`` (less a hair for rounding), the others are left as they are. Every
        trainer's last step, so no network is stored over the bounds it states."""
        w0 = np.array(self.weights[0])
        for cols, bound in zip(blocks, bounds):
            cols = list(cols)
            cert = self.certified_lipschitz_columns(cols)
            if cert > bound:
                w0[:, cols] *= bound / cert * (1.0 - 1e-12)
        net = LipschitzMLP((w0, *self.weights[1:]), self.biases, self.input_mean, self.input_std, self.output_mean,
                           self.output_std, self.lipschitz_bound, dict(self.metadata), self.bound_units)
        for cols, bound in zip(blocks, bounds):
            if net.certified_lipschitz_columns(list(cols)) > bound:  # rounding of the SVD: shrink a relative 1e-9 more
                w0[:, list(cols)] *= 1.0 - 1e-9
                net = LipschitzMLP((w0, *self.weights[1:]), self.biases, self.input_mean, self.input_std,
                                   self.output_mean, self.output_std, self.lipschitz_bound, dict(self.metadata),
                                   self.bound_units)
        return net

    def scaled_to_bound(self, bound: float, units: str | None = None, *, all_inputs: bool = False) -> LipschitzMLP:
        """A copy whose certificate in ``units`` (default: its ``bound_units``) is ``<= bound``, stating
        ``lipschitz_bound = bound`` in those units. ``all_inputs`` (physical units only): the certificate of
        every input (Lemma 1's ``L_N``) rather than of the state inputs.

        If the certificate ``C`` exceeds ``bound``, each weight is multiplied by
        ``c = (bound / C)^(1/n)`` and bias ``i`` (0-based) by ``c^(i+1)``. Since ReLU is positively
        homogeneous, the normalised map becomes exactly ``c^n * h_n`` (same shape, flatter slope).
        A hair of extra shrink absorbs float rounding in the SVD product. Otherwise the weights
        are copied unchanged.
        """
        bound = float(bound)
        if units is not None and units != self.bound_units:
            restated = LipschitzMLP(self.weights, self.biases, self.input_mean, self.input_std, self.output_mean,
                                    self.output_std, bound, dict(self.metadata), units)
            return restated.scaled_to_bound(bound, all_inputs=all_inputs)
        if all_inputs and self.bound_units != "physical":
            raise ValueError("all_inputs is a physical certificate")
        certificate = self.certified_lipschitz_physical if all_inputs else self.certified_lipschitz
        cert = certificate()
        ws, bs = list(self.weights), list(self.biases)
        if cert > bound:
            n = len(ws)
            c = (bound / cert) ** (1.0 / n)
            ws = [w * c for w in ws]
            bs = [b * c ** (i + 1) for i, b in enumerate(bs)]
            new = LipschitzMLP(tuple(ws), tuple(bs), self.input_mean, self.input_std, self.output_mean,
                               self.output_std, bound, dict(self.metadata), self.bound_units)
            new_cert = (new.certified_lipschitz_physical if all_inputs else new.certified_lipschitz)()
            if new_cert > bound:  # rounding: shrink the last layer only, by a relative ~1e-15
                f = bound / new_cert * (1.0 - 1e-12)
                ws[-1] = ws[-1] * f
                bs[-1] = bs[-1] * f
        return LipschitzMLP(tuple(ws), tuple(bs), self.input_mean, self.input_std,
                            self.output_mean, self.output_std, bound, dict(self.metadata), self.bound_units)
