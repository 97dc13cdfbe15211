"""Training to a physical Lipschitz budget that the network can actually spend.

The certificate counts the network's slope in physical units, (m/s²) per unit of each input, Euclidean
over the inputs' mixed units. Projected Adam on z-scored inputs (the paper's recipe, kept in
:mod:`neso.training` for the ``normalised`` bound) spends such a budget badly: z-scoring multiplies a
quiet input's column by ``1/σ`` (roll, σ = 0.0126 rad on real PX4 flights: ×79), every Adam step moves it
as much as any other, and the uniform rescale after each step then takes the budget from the inputs that
carry the signal. This trainer instead:

* **parametrises the bound exactly, in physical units.** The first layer acts on the centred physical
  input ``z − μ``; its columns are split into blocks (``blocks``; by default one block of all inputs), each
  block normalised by its exact spectral norm and given a gain ``g_b = L_b · sigmoid(ρ_b)``; every other
  layer is normalised to spectral norm 1. So the network's Lipschitz constant in block ``b`` is at most
  ``g_b < L_b`` by construction (ReLU is 1-Lipschitz), every step of the optimiser stays certified, and
  the gradient sees what spending budget on a column costs (the normalisation is differentiated through).
* **starts from the best linear map inside the bound** (:func:`neso.linear_fit.bounded_linear_fit`),
  written into the network exactly (one path whose ReLUs stay active over the data, plus small random
  paths for the rest to grow), or from the warm-start network when that is better on validation (TDR).
* **fits the output offset exactly** after every epoch (the last bias: the training residual's mean is
  0; a bias does not change the slope).
* **stops on validation**: the split is by blocks of consecutive samples (neighbouring samples of a flight
  are nearly the same sample), the network of the best validation epoch is kept (epoch 0 is the start),
  and training stops after ``patience`` epochs without improvement.

The exported :class:`neso.network.LipschitzMLP` is the same function in the usual layout (z-scores at
both ends); its certificates are recomputed from the weights by exact SVD products, as for any network.
"""
from __future__ import annotations

import math

import numpy as np

from neso.linear_fit import BoundedLinearFit, bounded_linear_fit
from neso.network import LipschitzMLP, fold_scalers

#: The start's extra paths are this small relative to the fitted path: enough to give them gradients.
_SEED_SCALE = 1e-2
#: A gain never starts closer to its bound than this fraction (the sigmoid's end).
_GAIN_CAP = 1.0 - 1e-6
_EPS = 1e-12


def block_split(n: int, val_fraction: float, seed: int, block: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) indices: the samples cut into runs of ``block`` consecutive ones, a seeded
    ``val_fraction`` of the runs held out."""
    starts = np.arange(0, n, max(1, block))
    perm = np.random.default_rng(seed).permutation(len(starts))
    n_val = int(round(val_fraction * len(starts)))
    if val_fraction > 0 and n_val == 0 and len(starts) > 1:
        n_val = 1
    val_runs = np.sort(starts[perm[:n_val]])
    is_val = np.zeros(n, dtype=bool)
    for s in val_runs:
        is_val[s:s + block] = True
    if is_val.all():
        raise ValueError("no training samples left after the split")
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def default_block(n: int) -> int:
    """Consecutive samples per validation run: 50 (1 s at 50 Hz), fewer for small sets (≥ 20 runs)."""
    return max(1, min(50, n // 20))


class _Layers:
    """Physical layers ``(A_i, c_i)``: ``h_1 = ReLU(A_1 (z − μ) + c_1)``, …, ``f = A_n h_{n−1} + c_n``."""

    def __init__(self, mats: list[np.ndarray], biases: list[np.ndarray], mu: np.ndarray) -> None:
        self.mats, self.biases, self.mu = mats, biases, mu

    @staticmethod
    def of_network(net: LipschitzMLP, mu: np.ndarray) -> "_Layers":
        """A network's physical layers about the input centre ``mu`` (the same function exactly)."""
        mats = [np.array(w, dtype=float) for w in fold_scalers(net.weights, net.input_std, net.output_std)]
        biases = [np.array(b, dtype=float) for b in net.biases]
        biases[0] = biases[0] + mats[0] @ (mu - net.input_mean)
        biases[-1] = biases[-1] * net.output_std + net.output_mean
        return _Layers(mats, biases, np.array(mu, dtype=float))

    def normalised(self) -> "_Layers":
        """The same function with every layer but the first at spectral norm 1 (their norms pushed into the
        first layer, biases rescaled: ReLU is positively homogeneous)."""
        norms = [max(float(np.linalg.norm(a, 2)), _EPS) for a in self.mats[1:]]
        scale = float(np.prod(norms))
        mats = [self.mats[0] * scale] + [a / s for a, s in zip(self.mats[1:], norms)]
        biases, running = [self.biases[0] * scale], scale
        for b, s in zip(self.biases[1:], norms):
            running /= s
            biases.append(b * running)
        return _Layers(mats, biases, self.mu)

    def export(self, mean_z, std_z, mean_y, std_y, bound: float, units: str = "physical") -> LipschitzMLP:
        """The usual layout: z-scored input (``std_z``), z-scored output (``mean_y``, ``std_y``)."""
        ws = [np.array(a) for a in self.mats]
        bs = [np.array(b) for b in self.biases]
        bs[0] = bs[0] + ws[0] @ (mean_z - self.mu)
        ws[0] = ws[0] * std_z[None, :]
        ws[-1] = ws[-1] / std_y
        bs[-1] = (bs[-1] - mean_y) / std_y
        return LipschitzMLP(tuple(ws), tuple(bs), mean_z, std_z, np.array([mean_y]), np.array([std_y]), bound,
                            bound_units=units)


def linear_layers(fit: BoundedLinearFit, z_train: np.ndarray, mu: np.ndarray, sizes: tuple[int, ...],
                  seed: int) -> _Layers:
    """A ReLU network equal to ``fit`` on the training inputs' range (and flat far outside it): the map
    rides one path whose units stay active with a margin of 3σ beyond the data, plus paths of relative size
    ``_SEED_SCALE`` for training to grow."""
    rng = np.random.default_rng(seed)
    w = fit.slopes
    proj = (z_train - mu) @ w
    scale = max(float(np.linalg.norm(w)), 1e-3)
    mats, biases = [], []
    for i in range(len(sizes) - 1):
        n_out, n_in = sizes[i + 1], sizes[i]
        a = rng.normal(size=(n_out, n_in)) * (_SEED_SCALE / math.sqrt(n_in)) * (scale if i == 0 else 1.0)
        b = np.abs(rng.normal(size=n_out)) * _SEED_SCALE * (float(np.std(proj)) + 1e-3)
        if i == 0:
            a[0] = w
            b[0] = -float(proj.min()) + 3.0 * float(np.std(proj)) + 1e-3
        elif i < len(sizes) - 2:
            a[0, :] = 0.0
            a[0, 0] = 1.0
            b[0] = 0.0
        else:
            a[0, 0] = 1.0
            b[:] = 0.0
        mats.append(a)
        biases.append(b)
    return _Layers(mats, biases, mu)


class _Torch:
    """The parametrised network in torch (module docstring): first-layer blocks with gains, the rest at norm 1."""

    def __init__(self, layers: _Layers, blocks, bounds, torch) -> None:
        self.torch, self.blocks, self.bounds = torch, blocks, bounds
        lay = layers.normalised()
        first = lay.mats[0]

        def t(a):
            return torch.tensor(np.asarray(a, dtype=np.float64), dtype=torch.float64, requires_grad=True)

        self.v_blocks, self.rho = [], []
        for cols, bound in zip(blocks, bounds):
            m = first[:, list(cols)]
            gain = float(np.linalg.norm(m, 2))
            frac = min(max(gain / bound, 1e-4), _GAIN_CAP)
            self.v_blocks.append(t(m / max(gain, _EPS) if gain > _EPS else m + 1e-3))
            self.rho.append(t(math.log(frac / (1.0 - frac))))
        self.v_rest = [t(a) for a in lay.mats[1:]]
        self.b = [t(b) for b in lay.biases]
        self.n_in = first.shape[1]
        self.mu = lay.mu

    def parameters(self) -> list:
        return [*self.v_blocks, *self.rho, *self.v_rest, *self.b]

    def _norm(self, v):
        return v / self.torch.clamp(self.torch.linalg.matrix_norm(v, ord=2), min=_EPS)

    def matrices(self):
        torch = self.torch
        first = torch.zeros((self.v_blocks[0].shape[0], self.n_in), dtype=torch.float64)
        for cols, v, rho, bound in zip(self.blocks, self.v_blocks, self.rho, self.bounds):
            first = first.index_add(1, torch.tensor(cols), bound * torch.sigmoid(rho) * self._norm(v))
        return [first] + [self._norm(v) for v in self.v_rest]

    def forward(self, x):
        mats = self.matrices()
        h = x
        for i, (a, b) in enumerate(zip(mats, self.b)):
            h = h @ a.T + b
            if i < len(mats) - 1:
                h = self.torch.relu(h)
        return h[:, 0]

    def layers(self) -> _Layers:
        with self.torch.no_grad():
            mats = [m.detach().numpy().copy() for m in self.matrices()]
            biases = [b.detach().numpy().copy() for b in self.b]
        return _Layers(mats, biases, self.mu)


def _fit_offset(layers: _Layers, z: np.ndarray, y: np.ndarray) -> _Layers:
    """The last bias set so the mean residual on (z, y) is 0."""
    pred = _predict(layers, z)
    biases = list(layers.biases)
    biases[-1] = biases[-1] + float(np.mean(y - pred))
    return _Layers(layers.mats, biases, layers.mu)


def _predict(layers: _Layers, z: np.ndarray) -> np.ndarray:
    h = np.asarray(z, dtype=float) - layers.mu
    last = len(layers.mats) - 1
    for i, (a, b) in enumerate(zip(layers.mats, layers.biases)):
        h = h @ a.T + b
        if i < last:
            h = np.maximum(h, 0.0)
    return h[:, 0]


def _mse(layers: _Layers, z: np.ndarray, y: np.ndarray) -> float:
    return float(np.mean((_predict(layers, z) - y) ** 2)) if len(y) else float("nan")


def train_physical(z: np.ndarray, y: np.ndarray, tr: np.ndarray, va: np.ndarray, *, blocks, bounds,
                   sizes: tuple[int, ...], epochs: int, lr: float, batch_size: int, seed: int,
                   init: LipschitzMLP | None, start: str, patience: int):
    """The module's training on ``z`` (N, n_in) physical and ``y`` (N,) with the given split.

    Returns ``(layers, info)``: the kept network's physical layers and a dict with ``start`` (``linear`` or
    ``init``), ``best_epoch``, ``epochs_run``, ``history`` (mean training loss per epoch, z-scored) and the
    bounded linear fit (``linear``)."""
    import torch

    zt_np, yt_np = z[tr], y[tr]
    zv_np, yv_np = z[va], y[va]
    mu = zt_np.mean(axis=0)
    y_std = max(float(yt_np.std()), 1e-6)
    fit = bounded_linear_fit(zt_np, yt_np, bounds=bounds, blocks=blocks)
    starts = {}
    if start in ("best", "linear") or init is None:
        starts["linear"] = _fit_offset(linear_layers(fit, zt_np, mu, sizes, seed), zt_np, yt_np)
    if init is not None and start in ("best", "init"):
        warm = _Layers.of_network(init, mu)
        starts["init"] = warm if start == "init" else _fit_offset(warm, zt_np, yt_np)

    def judge(lay: _Layers) -> float:
        return _mse(lay, zv_np, yv_np) if len(va) else _mse(lay, zt_np, yt_np)

    name = min(starts, key=lambda k: judge(starts[k]))
    best, best_loss, best_epoch = starts[name], judge(starts[name]), 0
    history: list[float] = []
    if epochs > 0:
        prev_threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            torch.manual_seed(seed)
            model = _Torch(best, blocks, bounds, torch)
            opt = torch.optim.Adam(model.parameters(), lr=lr)
            gen = torch.Generator().manual_seed(seed)
            x_all = torch.from_numpy(zt_np - mu)
            y_all = torch.from_numpy((yt_np - yt_np.mean()) / y_std)
            y_shift = torch.tensor(float(yt_np.mean()) / y_std, dtype=torch.float64)
            n_train, stale = len(yt_np), 0
            for epoch in range(1, epochs + 1):
                order = torch.randperm(n_train, generator=gen)
                total = 0.0
                for s in range(0, n_train, batch_size):
                    idx = order[s:s + batch_size]
                    out = model.forward(x_all[idx]) / y_std - y_shift
                    loss = torch.mean((out - y_all[idx]) ** 2)
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                    total += loss.item() * len(idx)
                history.append(total / n_train)
                current = _fit_offset(model.layers(), zt_np, yt_np)
                with torch.no_grad():  # the exact offset goes back into the model
                    model.b[-1].copy_(torch.from_numpy(np.asarray(current.biases[-1])))
                loss_now = judge(current)
                if loss_now < best_loss:
                    best, best_loss, best_epoch, stale = current, loss_now, epoch, 0
                else:
                    stale += 1
                    if stale >= patience:
                        break
        finally:
            torch.set_num_threads(prev_threads)
    return best, {"start": name, "best_epoch": best_epoch, "epochs_run": len(history), "history": history,
                  "linear": fit}
