"""Offline training of the Lipschitz-bounded MLP (paper Sec. "Constrained DNN Training").

Two trainers, chosen by the unit of the bound:

* ``bound_units="normalised"`` — the paper as published: inputs and labels z-scored, seeded 80/20
  shuffled split, Adam (1e-3), MSE, 100 epochs, ReLU MLP n_in -> 20 -> 25 -> 10 -> 1, and
  ``||h_n||_Lip <= L_N`` on the z-scored map kept by projecting every weight matrix
  ``W <- W * min(1, L_N^(1/n) / sigma_max(W))`` after each optimiser step (Neural-Lander style).
  Warm start (Total Disturbance Retraining, ``init``): the base network's layer sizes and weights start
  the fit; ``scalers="init"`` keeps its z-score statistics (the paper), ``scalers="fit"`` fits them on
  the new data and re-expresses the base network exactly under them
  (:meth:`LipschitzMLP.with_scalers`).
* ``bound_units="physical"`` — the bound the stability certificate needs, (m/s²) per unit z:
  :mod:`neso.physical_training` (the budget parametrised exactly in physical units so it goes to the
  inputs that carry the label, the start from the best linear map inside the bound, the offset fitted
  exactly, stopped on validation). Projected Adam on z-scores spent such a budget on the quietest input
  (measured on real PX4 flights: test R² 0.07 against 0.52 for a linear map inside the same bound).

Either way the exported numpy network is re-certified in float64, and every result says how its
validation loss compares with predicting the mean and what its physical slopes are.

torch is imported inside the functions only: importing this module must not pull torch into the
flight process.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from neso.network import BOUND_UNITS, LipschitzMLP

STD_FLOOR = 1e-6
SCALERS = ("fit", "init")


@dataclass(frozen=True, eq=False)
class TrainResult:
    """Outcome of ``train_lipschitz_mlp``.

    ``train_loss`` and ``val_loss`` are MSE on z-scored labels (dimensionless) of the exported
    network; ``val_loss_physical`` is the validation MSE in label units squared (e.g. (m/s^2)^2).
    ``history`` is the mean training minibatch loss of each epoch (z-scored).
    ``val_baseline_physical``: the validation MSE of predicting the training split's mean ((m/s²)²);
    ``val_loss_vs_mean`` = ``val_loss_physical / val_baseline_physical`` (< 1: better than the mean).
    ``slopes``: the mean physical slope ∂h/∂z_i over the training inputs, by input name.
    The validation figures are NaN when the validation split is empty.
    """

    network: LipschitzMLP
    train_loss: float
    val_loss: float
    val_loss_physical: float
    history: list[float] = field(default_factory=list)
    n_train: int = 0
    n_val: int = 0
    val_baseline_physical: float = float("nan")
    val_loss_vs_mean: float = float("nan")
    slopes: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class _Scalers:
    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: np.ndarray
    out_std: np.ndarray


def _zscore_stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return a.mean(axis=0), np.maximum(a.std(axis=0), STD_FLOOR)


def _check_inputs(z, y, bound: float, bound_units: str, val_fraction: float, scalers: str):
    z = np.asarray(z, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    if z.ndim != 2 or y.ndim != 2 or z.shape[0] != y.shape[0]:
        raise ValueError(f"need z (N, n_in) and y (N,) or (N, n_out); got {z.shape} and {y.shape}")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(y))):
        raise ValueError("training data contains NaN or inf")
    if not (np.isfinite(bound) and bound > 0):
        raise ValueError(f"lipschitz_bound must be finite and > 0, got {bound}")
    if bound_units not in BOUND_UNITS:
        raise ValueError(f"bound_units must be one of {BOUND_UNITS}, got {bound_units!r}")
    if scalers not in SCALERS:
        raise ValueError(f"scalers must be one of {SCALERS}, got {scalers!r}")
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    return z, y


def _split(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) indices of a seeded shuffle."""
    perm = np.random.default_rng(seed).permutation(n)
    n_val = int(round(val_fraction * n))
    if n - n_val < 1:
        raise ValueError("no training samples left after the split")
    return perm[n_val:], perm[:n_val]


def _start(z_train: np.ndarray, y_train: np.ndarray, init: LipschitzMLP | None, scalers: str,
           hidden: tuple[int, ...]) -> tuple[_Scalers, tuple[int, ...], LipschitzMLP | None]:
    """The z-score statistics, the layer sizes and the warm-start network expressed under those statistics."""
    n_in, n_out = z_train.shape[1], y_train.shape[1]
    if init is None:
        return _Scalers(*_zscore_stats(z_train), *_zscore_stats(y_train)), (n_in, *hidden, n_out), None
    sizes = init.layer_sizes
    if sizes[0] != n_in or sizes[-1] != n_out:
        raise ValueError(f"init network is {sizes[0]} -> {sizes[-1]}, data is {n_in} -> {n_out}")
    if scalers == "init":
        return _Scalers(np.array(init.input_mean), np.array(init.input_std), np.array(init.output_mean),
                        np.array(init.output_std)), sizes, init
    stats = _Scalers(*_zscore_stats(z_train), *_zscore_stats(y_train))
    return stats, sizes, init.with_scalers(stats.in_mean, stats.in_std, stats.out_mean, stats.out_std)


class _Projection:
    """Keeps the torch layers inside the normalised bound after every step (module docstring)."""

    def __init__(self, linears, bound: float) -> None:
        self.linears = linears
        self.cap = bound ** (1.0 / len(linears))

    def __call__(self) -> None:
        import torch

        with torch.no_grad():
            for lin in self.linears:
                sigma = float(torch.linalg.matrix_norm(lin.weight, ord=2))
                if sigma > self.cap:
                    lin.weight.mul_(self.cap / sigma)


def _fit(linears, project: _Projection, zt, yt, *, epochs: int, lr: float, batch_size: int, seed: int, torch) -> list[float]:
    layers: list = []
    for i, lin in enumerate(linears):
        layers.append(lin)
        if i < len(linears) - 1:
            layers.append(torch.nn.ReLU())
    model = torch.nn.Sequential(*layers)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    n_train = zt.shape[0]
    history: list[float] = []
    for _ in range(epochs):
        order = torch.randperm(n_train, generator=gen)
        total = 0.0
        for start in range(0, n_train, batch_size):
            idx = order[start:start + batch_size]
            loss = torch.mean((model(zt[idx]) - yt[idx]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            project()
            total += loss.item() * len(idx)
        history.append(total / n_train)
    return history


def train_lipschitz_mlp(
    z: np.ndarray,
    y: np.ndarray,
    *,
    lipschitz_bound: float,
    bound_units: str = "normalised",
    hidden: tuple[int, ...] = (20, 25, 10),
    epochs: int = 100,
    lr: float = 1e-3,
    batch_size: int = 64,
    val_fraction: float = 0.2,
    seed: int = 0,
    init: LipschitzMLP | None = None,
    scalers: str = "init",
    metadata: dict[str, str] | None = None,
    blocks: tuple[tuple[int, ...], ...] | None = None,
    block_bounds: tuple[float, ...] | None = None,
    start: str = "best",
    patience: int = 25,
    column_names: tuple[str, ...] | None = None,
) -> TrainResult:
    """Fit ``h`` with its Lipschitz constant ``<= lipschitz_bound`` in ``bound_units``.

    ``z`` shape ``(N, n_in)`` physical units; ``y`` shape ``(N,)`` or ``(N, n_out)``.

    ``normalised`` (the paper): projected Adam on z-scored data, a seeded shuffled 80/20 split, every
    epoch run; ``init`` and ``scalers`` the warm start (module docstring).

    ``physical``: :mod:`neso.physical_training` (the budget parametrised exactly in physical units, the
    start from the best bounded linear map or ``init``, whichever validates better (``start``: ``best``,
    ``linear`` or ``init``), the offset fitted exactly, a split by runs of consecutive samples, the best
    validation epoch kept, stopped after ``patience`` epochs without improvement). ``blocks``/
    ``block_bounds``: column groups with a bound each (default: all columns under ``lipschitz_bound``).
    One output only.

    The z-score statistics (std floored at 1e-6) come from the training split only, so validation is
    honest. Deterministic for a given ``seed`` (single torch thread). ``column_names`` label the per-input
    slopes in the metadata.
    """
    bound = float(lipschitz_bound)
    z, y = _check_inputs(z, y, bound, bound_units, val_fraction, scalers)
    if bound_units == "physical":
        return _train_physical(z, y, bound, hidden=hidden, epochs=epochs, lr=lr, batch_size=batch_size,
                               val_fraction=val_fraction, seed=seed, init=init, scalers=scalers, metadata=metadata,
                               blocks=blocks, block_bounds=block_bounds, start=start, patience=patience,
                               column_names=column_names)
    import torch

    tr, va = _split(z.shape[0], val_fraction, seed)
    stats, sizes, start_net = _start(z[tr], y[tr], init, scalers, hidden)
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(seed)
        linears = [torch.nn.Linear(sizes[i], sizes[i + 1]) for i in range(len(sizes) - 1)]
        if start_net is not None:
            with torch.no_grad():
                for lin, w, b in zip(linears, start_net.weights, start_net.biases):
                    lin.weight.copy_(torch.from_numpy(np.array(w)))
                    lin.bias.copy_(torch.from_numpy(np.array(b)))
        project = _Projection(linears, bound)
        project()
        zt = torch.from_numpy(((z[tr] - stats.in_mean) / stats.in_std).astype(np.float32))
        yt = torch.from_numpy(((y[tr] - stats.out_mean) / stats.out_std).astype(np.float32))
        history = _fit(linears, project, zt, yt, epochs=epochs, lr=lr, batch_size=batch_size, seed=seed, torch=torch)
        weights = tuple(lin.weight.detach().double().numpy().copy() for lin in linears)
        biases = tuple(lin.bias.detach().double().numpy().copy() for lin in linears)
    finally:
        torch.set_num_threads(prev_threads)

    net = LipschitzMLP(weights, biases, stats.in_mean, stats.in_std, stats.out_mean, stats.out_std, bound,
                       bound_units=bound_units)
    net = net.scaled_to_bound(bound)  # no-op unless float32 rounding left it a hair over
    extra = {"split": "shuffled samples", "trainer": "projected Adam (normalised bound)"}
    return _result(net, z, y, tr, va, history, init, epochs, lr, batch_size, seed, scalers, metadata, extra,
                   column_names)


def _train_physical(z, y, bound, *, hidden, epochs, lr, batch_size, val_fraction, seed, init, scalers, metadata,
                    blocks, block_bounds, start, patience, column_names) -> TrainResult:
    from neso.physical_training import block_split, default_block, train_physical

    if y.shape[1] != 1:
        raise ValueError(f"a physical bound trains one output, got {y.shape[1]}")
    if start not in ("best", "linear", "init"):
        raise ValueError(f"start must be best, linear or init, got {start!r}")
    n_in = z.shape[1]
    blocks = (tuple(range(n_in)),) if blocks is None else tuple(tuple(b) for b in blocks)
    block_bounds = (bound,) if block_bounds is None else tuple(float(b) for b in block_bounds)
    sizes = init.layer_sizes if init is not None else (n_in, *hidden, 1)
    if sizes[0] != n_in:
        raise ValueError(f"init network is {sizes[0]} -> {sizes[-1]}, data is {n_in} -> 1")
    run = default_block(len(y))
    tr, va = block_split(len(y), val_fraction, seed, run)
    layers, info = train_physical(z, y[:, 0], tr, va, blocks=blocks, bounds=block_bounds, sizes=sizes, epochs=epochs,
                                  lr=lr, batch_size=batch_size, seed=seed, init=init, start=start, patience=patience)
    in_mean, in_std = _zscore_stats(z[tr])
    out_mean, out_std = _zscore_stats(y[tr])
    net = layers.export(in_mean, in_std, float(out_mean[0]), float(out_std[0]), bound)
    # the kept network may be the start (a linear fit at its bound plus small paths, or a warm start made for a
    # higher bound): every block is brought within its bound before anything is stored
    net = net.within_block_bounds(blocks, block_bounds)
    extra = {"split": f"runs of {run} consecutive samples", "trainer": "physical budget, exact parametrisation",
             "start": info["start"], "best_epoch": str(info["best_epoch"]), "epochs_run": str(info["epochs_run"]),
             "linear_fit_slopes": json.dumps([round(float(v), 6) for v in info["linear"].slopes])}
    if len(blocks) > 1:
        extra["blocks"] = json.dumps([list(b) for b in blocks])
        extra["block_bounds"] = json.dumps(list(block_bounds))
    return _result(net, z, y, tr, va, info["history"], init, epochs, lr, batch_size, seed, scalers, metadata, extra,
                   column_names)


def _result(net, z, y, tr, va, history, init, epochs, lr, batch_size, seed, scalers, metadata, extra=None,
            column_names=None) -> TrainResult:
    def losses(idx: np.ndarray) -> tuple[float, float]:
        if idx.size == 0:
            return float("nan"), float("nan")
        err = net.predict(z[idx]) - y[idx]
        return float(np.mean((err / net.output_std) ** 2)), float(np.mean(err ** 2))

    train_loss, _ = losses(tr)
    val_loss, val_loss_phys = losses(va)
    # What predicting the training split's mean would score on validation: the bar a network must clear.
    baseline = float(np.mean((y[va] - y[tr].mean(axis=0)) ** 2)) if va.size else float("nan")
    vs_mean = val_loss_phys / baseline if va.size and baseline > 0 else float("nan")
    slopes = net.input_gradients(z[tr]).mean(axis=0)[0] if net.n_outputs == 1 else np.full(net.n_inputs, np.nan)
    names = column_names if column_names is not None else _column_names(net, metadata)
    meta = {
        "n_train": str(len(tr)),
        "n_val": str(len(va)),
        "epochs": str(epochs),
        "lr": repr(float(lr)),
        "batch_size": str(batch_size),
        "seed": str(seed),
        "train_loss": repr(train_loss),
        "val_loss": repr(val_loss),
        "val_loss_physical": repr(val_loss_phys),
        "val_baseline_physical": repr(baseline),
        "val_loss_vs_mean": repr(vs_mean),
        "slopes": json.dumps({n: round(float(v), 6) for n, v in zip(names, slopes)}),
        "warm_start": init.metadata.get("id", "yes") if init is not None else "no",
    }
    if init is not None:
        meta["scalers"] = scalers
    meta.update(extra or {})
    meta.update({str(k): str(v) for k, v in (metadata or {}).items()})
    net = LipschitzMLP(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                       net.lipschitz_bound, meta, net.bound_units)
    return TrainResult(net, train_loss, val_loss, val_loss_phys, history, len(tr), len(va), baseline, vs_mean,
                       dict(zip(names, (float(v) for v in slopes))))


def _column_names(net: LipschitzMLP, metadata) -> tuple[str, ...]:
    """The feature set's column names when the metadata names one, else ``z0 … z(n−1)``."""
    from neso.features import feature_set

    key = (metadata or {}).get("feature_set")
    if key:
        fs = feature_set(key)
        if fs.size == net.n_inputs:
            return fs.columns
    return tuple(f"z{i}" for i in range(net.n_inputs))


def to_torch(net: LipschitzMLP, dtype=None):
    """``torch.nn.Sequential`` computing ``net.predict`` on ``(N, n_in)`` tensors (physical units).

    The z-scores are diagonal ``Linear`` layers at both ends; ``dtype`` defaults to float64.
    """
    import torch

    dtype = torch.float64 if dtype is None else dtype

    def linear(w: np.ndarray, b: np.ndarray) -> torch.nn.Linear:
        lin = torch.nn.Linear(w.shape[1], w.shape[0], dtype=dtype)
        with torch.no_grad():
            lin.weight.copy_(torch.from_numpy(np.array(w)))
            lin.bias.copy_(torch.from_numpy(np.array(b)))
        return lin

    mods = [linear(np.diag(1.0 / net.input_std), -net.input_mean / net.input_std)]
    for i, (w, b) in enumerate(zip(net.weights, net.biases)):
        mods.append(linear(w, b))
        if i < net.n_layers - 1:
            mods.append(torch.nn.ReLU())
    mods.append(linear(np.diag(net.output_std), net.output_mean))
    return torch.nn.Sequential(*mods)
