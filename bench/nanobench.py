"""``make bench`` rows: the real-flight benchmark the project owns, on NanoBench flights (Crazyflie 2.1, Vicon).

The flights are the subset shipped in ``tests/data/nanobench/`` (``train/`` and ``heldout/``; its README says what
was taken and how), imported by ``neso recordings import`` (:mod:`recordings.nanobench`): the training flights in
one import (their thrust scale is the median of their own fits), the held-out ones with that scale, so nothing of a
held-out flight reaches a predictor. Everything is measured against **the z residual**: the lag-consistent label
``applied`` (:mod:`neso.learning`: the measured acceleration and the thrust through the same 3 Hz zero-phase
low-pass, with the thrust lag ``neso train`` identified on the training flights), on the held-out flights' airborne
samples.

- **Fit** (open loop): the z residual's R² on the held-out flights (and within flights: each flight's own mean taken
  out of the residual and of the prediction, which is what a function of the state can explain; a flight's constant
  offset, here mostly its battery, is the observer's to remove) and RMS error of (a) the certified recipe, the
  default ``neso train --base`` (:func:`services.trainer.train_job`, mode ``base``: inputs ``state@1``, ESO-teacher
  labels, 0.9 × the largest bound the certificate allows for the gains), (a') the same with the recipe's
  lag-consistent label (``neso train --base --label applied``), (b) the paper recipe (inputs ``paper@1``,
  ESO-teacher labels, L_N = 1 normalised), (c) the best linear map inside (a)'s bound
  (:func:`neso.linear_fit.bounded_linear_fit`, (a)'s labels and blocks), (d) predicting (a)'s training labels' mean.
  With each, the mean slopes ∂f/∂p_z and ∂f/∂v_z over the held-out samples below ``near_ground_m``: ground effect
  makes thrust grow near the floor, so the residual falls with height there (∂f/∂p_z < 0), and drag opposes motion
  (∂f/∂v_z ≤ 0). The first row is the residual's own least-squares slope on p_z over the same samples.
- **By height**: the held-out residual's mean and each predictor's in bands of height above the rest height: the
  shape of the near-ground disturbance and how much of it each learned.
- **Estimate** (the observer replayed): the ESO alone and the neural ESO's composite f_N + Δf̂ with each network, run
  by ``neso replay --what-if pathway=neural_eso,network=…`` (:func:`recordings.replay.what_if`) over each held-out
  recording: RMS error and R² against the z residual, and the lag (the shift of the estimate that correlates best
  with the residual).

Gains and observer: the project's defaults (k_p 10, k_d 6 on z: ``neso.control.ControlConfig``; ω_o 15 rad/s:
``neso.types.OMEGA_O_RPS``), whose certified budget bounds (a), (a') and (c). The Crazyflie flew under its own
controller, so the gains only decide the bound a network must respect to fly under this project's controller.

    python -m bench.nanobench [--quick] [--dataset DIR] [--epochs N]
"""
from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SUBSET = Path(__file__).resolve().parents[1] / "tests" / "data" / "nanobench"
FIT_COLUMNS = ("z residual, held-out NanoBench flights", "R²", "R² within flights", "RMS m/s²", "∂f/∂p_z < 10 cm",
               "∂f/∂v_z < 10 cm")
ESTIMATE_COLUMNS = ("f̂ z against the residual (replayed)", "RMS error m/s²", "R²", "lag ms")
HEIGHT_BANDS_M = ((0.005, 0.02), (0.02, 0.05), (0.05, 0.10), (0.10, 0.30), (0.30, math.inf))
VEHICLE = "uav1"
RESIDUAL = "the residual itself (least squares on p_z)"
CERTIFIED = "(a) certified recipe (neso train --base)"
CERTIFIED_APPLIED = "(a') the same, lag-consistent label (--label applied)"
PAPER = "(b) paper recipe"
LINEAR = "(c) best linear map inside (a)'s bound"
MEAN = "(d) the training labels' mean"
ESO = "ESO alone"
COMPOSITE = {"a": "neural ESO, (a)'s network", "a'": "neural ESO, (a')'s network", "b": "neural ESO, (b)'s network"}


@dataclass(frozen=True)
class BenchConfig:
    """``networks``: which of (a), (a'), (b) to train (``"a"`` always: (c) and (d) use its training set);
    ``epochs``/``seed``: their training; ``near_ground_m``: the slopes' band above the rest height (m);
    ``max_lag_s``: the lag search; gains (1/s², 1/s) and ω_o (rad/s) the certified bound is for (None: defaults)."""

    networks: tuple[str, ...] = ("a", "a'", "b")
    epochs: int = 100
    seed: int = 0
    near_ground_m: float = 0.10
    max_lag_s: float = 0.5
    kp: float | None = None
    kd: float | None = None
    omega_o_rps: float | None = None


def subset_files(subset: Path = SUBSET) -> tuple[list[Path], list[Path]]:
    """(training, held-out) CSVs of the shipped subset."""
    from recordings.nanobench import is_nanobench_csv

    def pick(split: str) -> list[Path]:
        return sorted(p for p in (subset / split).iterdir() if is_nanobench_csv(p))

    return pick("train"), pick("heldout")


def dataset_split(folder: str | Path, every: int = 4) -> tuple[list[Path], list[Path], list[tuple[Path, Path]]]:
    """(training, held-out, (copy, original) pairs) of a whole NanoBench ``datasets/dataset`` folder's CSVs:
    byte-identical copies dropped first (the first name of each kept, so a copy never lands on the other side), the
    rest sorted by name and every ``every``-th from the second held out."""
    import hashlib

    from recordings.nanobench import is_nanobench_csv

    unique: dict[str, Path] = {}
    copies = []
    for path in sorted(p for p in Path(folder).iterdir() if is_nanobench_csv(p)):
        first = unique.setdefault(hashlib.sha256(path.read_bytes()).hexdigest(), path)
        if first != path:
            copies.append((path, first))
    files = sorted(unique.values())
    return ([p for i, p in enumerate(files) if i % every != 1], [p for i, p in enumerate(files) if i % every == 1],
            copies)


def r2_within(y: np.ndarray, pred: np.ndarray, flight: np.ndarray) -> float:
    """R² of ``pred`` (N,) for ``y`` (N,) with each flight's (``flight`` (N,) labels) own mean taken out of both."""
    yc, pc = np.asarray(y, dtype=float).copy(), np.asarray(pred, dtype=float).copy()
    for f in np.unique(flight):
        m = flight == f
        yc[m] -= yc[m].mean()
        pc[m] -= pc[m].mean()
    return 1.0 - float(np.sum((yc - pc) ** 2)) / float(np.sum(yc ** 2))


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def mean_slope(predict, z: np.ndarray, column: int, step: float = 1e-3) -> float:
    """Mean ∂predict/∂z[:, column] over the rows of ``z`` (N, n): central differences of ``step`` (the column's
    unit)."""
    hi, lo = z.copy(), z.copy()
    hi[:, column] += step
    lo[:, column] -= step
    return float(np.mean((predict(hi) - predict(lo)) / (2 * step))) if len(z) else float("nan")


def best_lag_s(pairs: list[tuple[np.ndarray, np.ndarray]], dt_s: float, max_lag_s: float) -> float:
    """The shift τ ≥ 0 (s) that best correlates the estimate f[k + τ] with the residual y[k], pooled over ``pairs``
    of (y, f) runs of consecutive samples."""
    best, best_c = 0.0, -np.inf
    for shift in range(int(round(max_lag_s / dt_s)) + 1):
        ys = np.concatenate([y[:len(y) - shift] for y, _ in pairs if len(y) > shift])
        fs = np.concatenate([f[shift:] for y, f in pairs if len(y) > shift])
        c = float(np.corrcoef(ys, fs)[0, 1])
        if c > best_c:
            best, best_c = shift * dt_s, c
    return best


def _consecutive(seq: np.ndarray) -> list[slice]:
    cuts = np.flatnonzero(np.diff(seq) != 1) + 1
    bounds = [0, *cuts.tolist(), len(seq)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _gains(config: BenchConfig) -> tuple[float, float, float]:
    from neso.control import ControlConfig
    from neso.types import OMEGA_O_RPS

    return (config.kp if config.kp is not None else ControlConfig().kp[2],
            config.kd if config.kd is not None else ControlConfig().kd[2],
            config.omega_o_rps if config.omega_o_rps is not None else OMEGA_O_RPS)


def benchmark(train_files, heldout_files, workdir: str | Path, config: BenchConfig = BenchConfig()) -> dict:
    """Import, train, evaluate (module docstring); the figures: ``data``, ``gains``, ``fit``, ``by_height`` and
    ``estimate`` (by the rows' names), ``timings_s``. ``ValueError`` when no training or no held-out flight imports."""
    from neso.features import ThrustLag, feature_set
    from neso.learning import RECIPES, recipe_blocks, recipe_bound
    from neso.linear_fit import bounded_linear_fit, r_squared
    from neso.netfile import load_network, save_network
    from neso.training import train_lipschitz_mlp
    from recordings.dataset import load_training_set, select
    from recordings.nanobench import NanoBenchConfig, import_nanobench
    from recordings.reader import read_recording
    from recordings.replay import WhatIf, what_if
    from services.trainer import Job, TrainerConfig, train_job

    workdir = Path(workdir)
    kp, kd, omega_o = _gains(config)
    timings: dict[str, float] = {}
    started = time.perf_counter()
    train_run = import_nanobench(train_files, workdir / "train")
    held_run = import_nanobench(heldout_files, workdir / "heldout", NanoBenchConfig(thrust_scale=train_run.scale))
    refused = [why for _, why in train_run.refused + held_run.refused]
    if not train_run.imported or not held_run.imported:
        raise ValueError(f"nothing to benchmark: {len(train_run.imported)} training and {len(held_run.imported)} "
                         f"held-out flights imported; refused: {refused}")
    train_rrd = [str(r.path) for r in train_run.imported]
    held_rrd = [str(r.path) for r in held_run.imported]
    timings["import"] = time.perf_counter() - started

    networks: dict[str, tuple[object, str]] = {}  # key → (network, its file)
    train_info: dict[str, dict] = {}
    for key, label in (("a", None), ("a'", "applied")):
        if key != "a" and key not in config.networks:
            continue
        t = time.perf_counter()
        trainer = TrainerConfig(registry=str(workdir / f"registry-{key}"), kp=kp, kd=kd, omega_o_rps=omega_o)
        result = train_job(Job(1, tuple(train_rrd), "base", label, None, config.epochs, False, config.seed), trainer,
                           VEHICLE, None)
        networks[key] = (load_network(result.path), result.path)
        train_info[key] = {k: result.info.get(k) for k in ("label", "certified_phys", "val_loss_vs_mean", "slopes")}
        timings[f"train ({key})"] = time.perf_counter() - t
    recipe = RECIPES["certified"]
    fset = feature_set(recipe.feature_set)
    meta = networks["a"][0].metadata  # the thrust lag train_job identified on the training flights
    lag = ThrustLag(float(meta["thrust_lag_s"]), float(meta["thrust_delay_s"]))
    ts = load_training_set(train_rrd, recipe.base_label, feature_set_key=fset.key, lag=lag)  # (a)'s pairs
    bound = recipe_bound(recipe, kp, kd, omega_o)
    blocks, block_bounds = recipe_blocks(recipe, fset, bound)
    linear = bounded_linear_fit(ts.z, ts.y_mps2, bounds=block_bounds or bound, blocks=blocks)
    mean_label = float(np.mean(ts.y_mps2))
    paper = RECIPES["paper"]
    paper_fset = feature_set(paper.feature_set)
    if "b" in config.networks:
        t = time.perf_counter()
        ts_paper = load_training_set(train_rrd, paper.base_label, feature_set_key=paper_fset.key, lag=lag)
        net = train_lipschitz_mlp(ts_paper.z, ts_paper.y_mps2, lipschitz_bound=paper.lipschitz_bound,
                                  bound_units=paper.bound_units, epochs=config.epochs, seed=config.seed,
                                  metadata={"id": "nanobench-paper", "vehicle": VEHICLE, "feature_set": paper_fset.key,
                                            "recipe": paper.name, "label": paper.base_label}).network
        path = workdir / "paper" / "nanobench-paper.safetensors"
        path.parent.mkdir(parents=True, exist_ok=True)
        save_network(path, net)
        networks["b"] = (net, str(path))
        timings["train (b)"] = time.perf_counter() - t

    # the held-out residual, with each predictor's inputs, per recording
    t = time.perf_counter()
    parts: dict[str, list] = {"z": [], "z_paper": [], "y": [], "seq": [], "flight": []}
    for i, path in enumerate(held_rrd):
        rec = read_recording(path)
        sel = select(rec, "applied", fset, lag)
        parts["z"].append(sel.z)
        parts["z_paper"].append(select(rec, "applied", paper_fset, lag).z)
        parts["y"].append(sel.y_mps2)
        parts["seq"].append(sel.seq)
        parts["flight"].append(np.full(len(sel.seq), i))
    z, z_paper, y, flight = (np.concatenate(parts[k]) for k in ("z", "z_paper", "y", "flight"))
    pz = fset.columns.index("pos_z_m")
    near = z[:, pz] < config.near_ground_m
    predictors = {CERTIFIED: ("a", z, fset), CERTIFIED_APPLIED: ("a'", z, fset), PAPER: ("b", z_paper, paper_fset)}
    candidates = {name: (lambda q, net=networks[key][0]: net.predict(q).ravel(), zz, fs)
                  for name, (key, zz, fs) in predictors.items() if key in networks}
    candidates[LINEAR] = (linear.predict, z, fset)
    candidates[MEAN] = (lambda q: np.full(len(q), mean_label), z, fset)
    nan = float("nan")
    fit = {RESIDUAL: {"r2": nan, "r2_within": nan, "rms_mps2": nan, "slope_vz": nan,
                      "slope_pz": float(np.polyfit(z[near, pz], y[near], 1)[0]) if near.sum() > 2 else nan}}
    for name, (predict, zz, fs) in candidates.items():
        pred = predict(zz)
        fit[name] = {"r2": r_squared(y, pred), "r2_within": r2_within(y, pred, flight), "rms_mps2": rms(y - pred),
                     "slope_pz": mean_slope(predict, zz[near], fs.columns.index("pos_z_m")),
                     "slope_vz": mean_slope(predict, zz[near], fs.columns.index("vel_z_mps"))}
    by_height = []  # the residual's shape: its mean and each predictor's, per band of height above the rest height
    for lo, hi in HEIGHT_BANDS_M:
        band = (z[:, pz] >= lo) & (z[:, pz] < hi)
        by_height.append({"band_m": [lo, hi], "samples": int(band.sum()),
                          "mean_mps2": {RESIDUAL: float(np.mean(y[band])) if band.any() else nan,
                                        **{name: float(np.mean(predict(zz[band]))) if band.any() else nan
                                           for name, (predict, zz, _) in candidates.items() if name != MEAN}}})
    timings["evaluate fit"] = time.perf_counter() - t

    # the observer replayed over each held-out recording: the ESO alone and the composite with each network
    t = time.perf_counter()
    replays = {ESO: WhatIf(pathway="eso", omega_o_rps=omega_o),
               **{COMPOSITE[k]: WhatIf(pathway="neural_eso", network=str(path), omega_o_rps=omega_o)
                  for k, (_, path) in networks.items()}}
    pairs: dict[str, list] = {name: [] for name in replays}
    dt = []
    for path, seq, yy in zip(held_rrd, parts["seq"], parts["y"]):
        rec = read_recording(path)
        dt.append(float(np.median(np.diff(np.asarray(rec.channel("state").columns["t_s"], dtype=float)))))
        for name, change in replays.items():
            cmp = what_if(rec, change)
            common, ia, ib = np.intersect1d(seq, cmp.seq, return_indices=True)
            pairs[name] += [(yy[ia][part], cmp.f_hat_whatif_mps2[ib, 2][part]) for part in _consecutive(common)]
    estimate = {}
    for name, runs in pairs.items():
        yy = np.concatenate([p[0] for p in runs])
        ff = np.concatenate([p[1] for p in runs])
        estimate[name] = {"rms_mps2": rms(yy - ff), "r2": r_squared(yy, ff),
                          "lag_s": best_lag_s(runs, float(np.median(dt)), config.max_lag_s), "samples": int(len(yy))}
    timings["evaluate estimate"] = time.perf_counter() - t
    return {
        "data": {"train_flights": [r.flight.info["file_name"] for r in train_run.imported],
                 "heldout_flights": [r.flight.info["file_name"] for r in held_run.imported],
                 "refused": refused, "thrust_scale": train_run.scale, "train_samples": int(len(ts.y_mps2)),
                 "heldout_samples": int(len(y)), "heldout_near_ground_samples": int(near.sum()),
                 "near_ground_m": config.near_ground_m,
                 "thrust_lag_s": {"time_constant": lag.time_constant_s, "delay": lag.delay_s}},
        "gains": {"kp": kp, "kd": kd, "omega_o_rps": omega_o, "state_bound_phys": bound, "trained": train_info},
        "epochs": config.epochs, "seed": config.seed, "fit": fit, "by_height": by_height, "estimate": estimate,
        "timings_s": timings,
    }


def _fmt(v, spec: str) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def _band(lo: float, hi: float) -> str:
    return f"{lo * 100:g}–{hi * 100:g} cm" if math.isfinite(hi) else f"above {lo * 100:g} cm"


def table_rows(figures: dict) -> tuple[list[tuple[str, ...]], list[tuple[str, ...]], tuple[str, ...],
                                       list[tuple[str, ...]]]:
    """(fit rows, estimate rows, by-height columns, by-height rows); the first two for :data:`FIT_COLUMNS` and
    :data:`ESTIMATE_COLUMNS`."""
    fit = [(name, _fmt(f["r2"], ".3f"), _fmt(f["r2_within"], ".3f"), _fmt(f["rms_mps2"], ".3f"),
            _fmt(f["slope_pz"], "+.2f"), _fmt(f["slope_vz"], "+.2f")) for name, f in figures["fit"].items()]
    est = [(name, _fmt(e["rms_mps2"], ".3f"), _fmt(e["r2"], ".3f"), f"{e['lag_s'] * 1e3:.0f}")
           for name, e in figures["estimate"].items()]
    names = list(figures["by_height"][0]["mean_mps2"])
    columns = ("mean z residual m/s², held-out, by height", "samples",
               *(n.split(" ")[0] if n != RESIDUAL else "residual" for n in names))
    height = [(_band(*b["band_m"]), str(b["samples"]), *(_fmt(b["mean_mps2"][n], "+.2f") for n in names))
              for b in figures["by_height"]]
    return fit, est, columns, height


def summary(figures: dict) -> str:
    d, g = figures["data"], figures["gains"]
    return (f"NanoBench: {len(d['train_flights'])} training flights ({d['train_samples']} ESO-teacher pairs), "
            f"{len(d['heldout_flights'])} held-out ({d['heldout_samples']} residual samples, "
            f"{d['heldout_near_ground_samples']} below {d['near_ground_m'] * 100:g} cm); thrust scale "
            f"{d['thrust_scale']:.4f}; k_p {g['kp']:g}, k_d {g['kd']:g}, ω_o {g['omega_o_rps']:g} rad/s: state bound "
            f"{g['state_bound_phys']:.3f} (m/s²)/unit; {figures['epochs']} epochs")


def nanobench_rows(quick: bool = False, print_table=None, *, dataset: str | None = None, epochs: int | None = None,
                   key: str = "nanobench") -> dict:
    """The section: the benchmark on the shipped subset (``dataset``: a whole NanoBench ``datasets/dataset`` folder
    instead, :func:`dataset_split`; ``quick``: 30 epochs instead of 100), its two tables, its figures into
    ``out/bench.json`` under ``key``."""
    from bench.table import print_table as default_print, write_results

    print_table = print_table or default_print
    train, held, copies = (*subset_files(), []) if dataset is None else dataset_split(dataset)
    for copy, original in copies:
        print(f"left out: {copy}: byte-identical to {original}")
    with tempfile.TemporaryDirectory(prefix="neso-bench-nanobench-") as tmp:
        figures = benchmark(train, held, tmp, BenchConfig(epochs=epochs or (30 if quick else 100)))
    fit, est, height_columns, height = table_rows(figures)
    print(summary(figures), flush=True)
    print_table(FIT_COLUMNS, fit)
    print(flush=True)
    print_table(height_columns, height)
    print(flush=True)
    print_table(ESTIMATE_COLUMNS, est)
    write_results({key: figures})
    return figures


def main(argv: list[str]) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m bench.nanobench", description=__doc__.split("\n", 1)[0])
    parser.add_argument("--quick", action="store_true", help="30 epochs (as make bench-quick)")
    parser.add_argument("--dataset", default=None, help="a whole NanoBench datasets/dataset folder instead of the "
                                                        "shipped subset (every 4th unique flight held out)")
    parser.add_argument("--epochs", type=int, default=None, help="training epochs (default 100, 30 with --quick)")
    args = parser.parse_args(argv)
    figures = nanobench_rows(args.quick, dataset=args.dataset, epochs=args.epochs,
                             key="nanobench" if args.dataset is None else "nanobench_dataset")
    for why in figures["data"]["refused"]:
        print(f"refused: {why}")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
