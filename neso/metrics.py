"""Flight metrics of the paper's tables, on arrays (no I/O). Errors in metres unless named _cm."""
from __future__ import annotations

import numpy as np


def steady_state_abs_error_m(t_s: np.ndarray, error_m: np.ndarray, *, start_s: float) -> float:
    """Mean |error| over t ≥ ``start_s`` (t_s, error_m: (N,))."""
    window = t_s >= start_s
    if not np.any(window):
        raise ValueError("steady-state window is empty")
    return float(np.mean(np.abs(error_m[window])))


def settling_time_s(t_s: np.ndarray, error_m: np.ndarray, *, from_s: float, band_m: float) -> float:
    """Time after ``from_s`` from which |error| stays within ``band_m`` to the end; inf if never."""
    after = t_s >= from_s
    outside = np.flatnonzero(after & (np.abs(error_m) > band_m))
    if outside.size == 0:
        return 0.0
    last = outside[-1]
    if last + 1 >= t_s.size:
        return float("inf")
    return float(t_s[last + 1] - from_s)


def rmse_m(t_s: np.ndarray, error_m: np.ndarray, *, start_s: float, end_s: float = np.inf) -> float:
    """Root mean square of the error over [start_s, end_s)."""
    window = (t_s >= start_s) & (t_s < end_s)
    if not np.any(window):
        raise ValueError("RMSE window is empty")
    return float(np.sqrt(np.mean(error_m[window] ** 2)))


def summarise(trials: list[float | None]) -> dict:
    """The experiments' RESULT shape: mean/std over finite trials, None for diverged ones."""
    finite = [x for x in trials if x is not None and np.isfinite(x)]
    diverged = sum(1 for x in trials if x is None or not np.isfinite(x))
    return {
        "mean": float(np.mean(finite)) if finite else None,
        "std": float(np.std(finite)) if finite else None,
        "trials": [None if (x is None or not np.isfinite(x)) else float(x) for x in trials],
        "diverged": diverged,
    }
