"""Offline training of the Lipschitz-bounded MLP (paper Sec. "Constrained DNN Training").

Setup as in the paper: inputs and labels z-scored, seeded 80/20 shuffled split, Adam (1e-3), MSE,
100 epochs, ReLU MLP 5 -> 20 -> 25 -> 10 -> 1. The constraint ``||h_n||_Lip <= L_N`` (normalised
units) is enforced Neural-Lander style: after every optimiser step each weight matrix is projected
``W <- W * min(1, L_N^(1/n_layers) / sigma_max(W))`` with the exact largest singular value, so the
product of spectral norms, an upper bound on the Lipschitz constant of a ReLU net, is <= L_N at
every step. The exported numpy network is re-certified in float64 and rescaled by a hair if float32
rounding put it over.

torch is imported inside the functions only: importing this module must not pull torch into the
flight process.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from neso.network import LipschitzMLP

STD_FLOOR = 1e-6


@dataclass(frozen=True, eq=False)
class TrainResult:
    """Outcome of ``train_lipschitz_mlp``.

    ``train_loss`` and ``val_loss`` are MSE on z-scored labels (dimensionless) of the exported
    network; ``val_loss_physical`` is the validation MSE in label units squared (e.g. (m/s^2)^2).
    ``history`` is the mean training minibatch loss of each epoch (z-scored).
    ``val_loss``/``val_loss_physical`` are NaN when the validation split is empty.
    """

    network: LipschitzMLP
    train_loss: float
    val_loss: float
    val_loss_physical: float
    history: list[float] = field(default_factory=list)
    n_train: int = 0
    n_val: int = 0


def _zscore_stats(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return a.mean(axis=0), np.maximum(a.std(axis=0), STD_FLOOR)


def _project_(linears, cap: float, torch) -> None:
    """In-place ``W <- W * min(1, cap / sigma_max(W))`` for every layer (exact sigma_max)."""
    with torch.no_grad():
        for lin in linears:
            sigma = float(torch.linalg.matrix_norm(lin.weight, ord=2))
            if sigma > cap:
                lin.weight.mul_(cap / sigma)


def train_lipschitz_mlp(
    z: np.ndarray,
    y: np.ndarray,
    *,
    lipschitz_bound: float,
    hidden: tuple[int, ...] = (20, 25, 10),
    epochs: int = 100,
    lr: float = 1e-3,
    batch_size: int = 64,
    val_fraction: float = 0.2,
    seed: int = 0,
    init: LipschitzMLP | None = None,
    metadata: dict[str, str] | None = None,
) -> TrainResult:
    """Fit ``h`` with ``||h_n||_Lip <= lipschitz_bound`` (normalised units) by projected Adam.

    ``z`` shape ``(N, n_in)`` physical units; ``y`` shape ``(N,)`` or ``(N, n_out)``. The split is
    a seeded shuffle; the z-score statistics (std floored at 1e-6) are computed on the training
    split only, so validation is honest. Deterministic for a given ``seed`` (single torch thread).

    ``init`` (Total Disturbance Retraining): the base network is retrained — its layer sizes,
    weights *and normalisation statistics* are kept. Keeping the statistics is what makes the
    warm start meaningful (the weights were learned for those input scales), and it keeps the
    physical Lipschitz bound ``L_N·σ_y/min σ_z`` the stability certificate uses unchanged.
    Recomputing them on a flight that holds one altitude would divide the near-constant
    height by a σ of millimetres and amplify its noise into f_N. The initial weights are
    projected to the new bound before the first step.
    """
    import torch

    z = np.asarray(z, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    if z.ndim != 2 or y.ndim != 2 or z.shape[0] != y.shape[0]:
        raise ValueError(f"need z (N, n_in) and y (N,) or (N, n_out); got {z.shape} and {y.shape}")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(y))):
        raise ValueError("training data contains NaN or inf")
    bound = float(lipschitz_bound)
    if not (np.isfinite(bound) and bound > 0):
        raise ValueError(f"lipschitz_bound must be finite and > 0, got {bound}")
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    n, n_in = z.shape
    n_out = y.shape[1]

    perm = np.random.default_rng(seed).permutation(n)
    n_val = int(round(val_fraction * n))
    n_train = n - n_val
    if n_train < 1:
        raise ValueError("no training samples left after the split")
    tr, va = perm[n_val:], perm[:n_val]
    if init is not None:
        in_mean, in_std = np.array(init.input_mean), np.array(init.input_std)
        out_mean, out_std = np.array(init.output_mean), np.array(init.output_std)
    else:
        in_mean, in_std = _zscore_stats(z[tr])
        out_mean, out_std = _zscore_stats(y[tr])

    if init is not None:
        sizes = init.layer_sizes
        if sizes[0] != n_in or sizes[-1] != n_out:
            raise ValueError(f"init network is {sizes[0]} -> {sizes[-1]}, data is {n_in} -> {n_out}")
    else:
        sizes = (n_in, *hidden, n_out)
    n_layers = len(sizes) - 1
    cap = bound ** (1.0 / n_layers)

    prev_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(seed)
        linears = [torch.nn.Linear(sizes[i], sizes[i + 1]) for i in range(n_layers)]
        if init is not None:
            with torch.no_grad():
                for lin, w, b in zip(linears, init.weights, init.biases):
                    lin.weight.copy_(torch.from_numpy(np.array(w)))
                    lin.bias.copy_(torch.from_numpy(np.array(b)))
        _project_(linears, cap, torch)
        layers: list = []
        for i, lin in enumerate(linears):
            layers.append(lin)
            if i < n_layers - 1:
                layers.append(torch.nn.ReLU())
        model = torch.nn.Sequential(*layers)

        zt = torch.from_numpy(((z[tr] - in_mean) / in_std).astype(np.float32))
        yt = torch.from_numpy(((y[tr] - out_mean) / out_std).astype(np.float32))
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(seed)
        history: list[float] = []
        for _ in range(epochs):
            order = torch.randperm(n_train, generator=gen)
            total = 0.0
            for start in range(0, n_train, batch_size):
                idx = order[start:start + batch_size]
                pred = model(zt[idx])
                loss = torch.mean((pred - yt[idx]) ** 2)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                _project_(linears, cap, torch)
                total += loss.item() * len(idx)
            history.append(total / n_train)
        weights = tuple(lin.weight.detach().double().numpy().copy() for lin in linears)
        biases = tuple(lin.bias.detach().double().numpy().copy() for lin in linears)
    finally:
        torch.set_num_threads(prev_threads)

    net = LipschitzMLP(weights, biases, in_mean, in_std, out_mean, out_std, bound)
    net = net.scaled_to_bound(bound)  # no-op unless float32 rounding left it a hair over

    def losses(idx: np.ndarray) -> tuple[float, float]:
        if idx.size == 0:
            return float("nan"), float("nan")
        err = net.predict(z[idx]) - y[idx]
        return float(np.mean((err / out_std) ** 2)), float(np.mean(err ** 2))

    train_loss, _ = losses(tr)
    val_loss, val_loss_phys = losses(va)
    meta = {
        "n_train": str(n_train),
        "n_val": str(n_val),
        "epochs": str(epochs),
        "lr": repr(float(lr)),
        "batch_size": str(batch_size),
        "seed": str(seed),
        "train_loss": repr(train_loss),
        "val_loss": repr(val_loss),
        "val_loss_physical": repr(val_loss_phys),
        "warm_start": init.metadata.get("id", "yes") if init is not None else "no",
    }
    meta.update({str(k): str(v) for k, v in (metadata or {}).items()})
    net = LipschitzMLP(net.weights, net.biases, net.input_mean, net.input_std,
                       net.output_mean, net.output_std, bound, meta)
    return TrainResult(net, train_loss, val_loss, val_loss_phys, history, n_train, n_val)


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
