"""The best linear map inside a Lipschitz budget: least squares with a 2-norm bound per block of inputs.

``min_{w, c} mean((z w + c − y)²)`` subject to ``‖w_b‖₂ ≤ L_b`` for every block ``b`` of input columns
(physical units: the label's unit per unit of each input, Euclidean over the block's mixed units, as the
stability certificate counts them). A linear map's Lipschitz constant in a block is exactly ``‖w_b‖``, so
this is the function a certified network can always represent; :mod:`neso.training` starts from it.

Solved exactly through the dual: for multipliers ``λ_b ≥ 0``, ``w(λ) = (G + Λ)⁻¹ h`` with ``G`` the
inputs' covariance and ``h`` their covariance with the label; the dual function is concave in ``λ`` and its
partial derivative in ``λ_b`` is ``½(‖w_b(λ)‖² − L_b²)``, so cyclic coordinate ascent with an exact 1-D root
per block converges to the KKT point. Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BoundedLinearFit:
    """``predict(z) = z @ slopes + offset``. ``slopes`` (n_in,) in label units per input unit; ``offset`` in
    label units; ``blocks``/``bounds`` the constraint it was fitted under; ``active`` whether each block's
    bound binds."""

    slopes: np.ndarray
    offset: float
    blocks: tuple[tuple[int, ...], ...]
    bounds: tuple[float, ...]
    active: tuple[bool, ...]

    def predict(self, z: np.ndarray) -> np.ndarray:
        """(N,) for ``z`` (N, n_in)."""
        return np.asarray(z, dtype=float) @ self.slopes + self.offset

    def block_norms(self) -> tuple[float, ...]:
        return tuple(float(np.linalg.norm(self.slopes[list(b)])) for b in self.blocks)


def r_squared(y: np.ndarray, prediction: np.ndarray) -> float:
    """``1 − Σ(y − ŷ)² / Σ(y − ȳ)²`` (NaN for a constant label)."""
    y = np.asarray(y, dtype=float).ravel()
    e = y - np.asarray(prediction, dtype=float).ravel()
    ss = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - float(np.sum(e ** 2)) / ss if ss > 0 else float("nan")


def bounded_linear_fit(z: np.ndarray, y: np.ndarray, *, bounds, blocks=None, sweeps: int = 500,
                       rtol: float = 1e-12) -> BoundedLinearFit:
    """The least-squares linear map with ``‖w_b‖ ≤ bounds[b]`` on each block (module docstring).

    ``z`` (N, n_in) physical, ``y`` (N,); ``blocks``: tuples of column indices covering every column once
    (default: one block of all columns); ``bounds``: one per block (> 0; ``inf`` for no bound).
    """
    z = np.asarray(z, dtype=float)
    y = np.asarray(y, dtype=float).ravel()
    if z.ndim != 2 or len(y) != len(z) or len(y) < 2:
        raise ValueError(f"need z (N, n) and y (N,) with N ≥ 2, got {z.shape} and {y.shape}")
    n_in = z.shape[1]
    blocks = ((tuple(range(n_in)),) if blocks is None else tuple(tuple(int(i) for i in b) for b in blocks))
    bounds = tuple(float(b) for b in (bounds if np.ndim(bounds) else [bounds]))
    if sorted(i for b in blocks for i in b) != list(range(n_in)):
        raise ValueError(f"blocks {blocks} must cover the {n_in} columns exactly once")
    if len(bounds) != len(blocks) or not all(b > 0 for b in bounds):
        raise ValueError(f"need one bound > 0 per block, got {bounds} for {len(blocks)} blocks")
    zm, ym = z.mean(axis=0), y.mean()
    zc = z - zm
    g = zc.T @ zc / len(y)
    h = zc.T @ (y - ym) / len(y)
    # A column that never moves has no slope to find; a hair of ridge keeps the solve defined.
    ridge = 1e-12 * max(float(np.trace(g)), 1e-300) / n_in
    lam = np.zeros(len(blocks))

    def solve(lam_vec: np.ndarray) -> np.ndarray:
        diag = np.full(n_in, ridge)
        for b, cols in enumerate(blocks):
            diag[list(cols)] += lam_vec[b]
        return np.linalg.solve(g + np.diag(diag), h)

    def excess(b: int, lam_vec: np.ndarray) -> float:
        return float(np.linalg.norm(solve(lam_vec)[list(blocks[b])])) - bounds[b]

    for _ in range(sweeps):
        before = lam.copy()
        for b in range(len(blocks)):
            if not np.isfinite(bounds[b]):
                continue
            trial = lam.copy()
            trial[b] = 0.0
            if excess(b, trial) <= 0.0:
                lam[b] = 0.0
                continue
            hi = max(lam[b], 1e-12 * max(float(np.trace(g)), 1e-300))
            while True:
                trial[b] = hi
                if excess(b, trial) <= 0.0:
                    break
                hi *= 2.0
            lo = 0.0
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                trial[b] = mid
                if excess(b, trial) > 0.0:
                    lo = mid
                else:
                    hi = mid
                if hi - lo <= rtol * hi:
                    break
            lam[b] = hi
        if np.allclose(lam, before, rtol=1e-10, atol=0.0):
            break
    w = solve(lam)
    for b, cols in enumerate(blocks):  # rounding: never report a map outside its bound
        norm = float(np.linalg.norm(w[list(cols)]))
        if norm > bounds[b]:
            w[list(cols)] *= bounds[b] / norm
    return BoundedLinearFit(w, float(ym - zm @ w), blocks, bounds, tuple(bool(v > 0) for v in lam))
