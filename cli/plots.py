"""PNG figures of a paper run (matplotlib, headless)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

COLORS = {"pd": "tab:gray", "pd_nn": "tab:orange", "pd_eso": "tab:blue", "neural_observer": "tab:purple",
          "neural_eso": "tab:red", "neural_eso_tdr": "tab:green"}


def _z_plot(ax, logs_by_method, title):
    for method, logs in logs_by_method.items():
        log = logs[0]
        ok = np.isfinite(log.t_s)
        ax.plot(log.t_s[ok], log.pos_true_m[ok, 2] * 100, label=method, color=COLORS.get(method), lw=1.2)
    ref = next(iter(logs_by_method.values()))[0]
    ok = np.isfinite(ref.t_s)
    ax.plot(ref.t_s[ok], ref.pos_ref_m[ok, 2] * 100, "k--", lw=1, label="reference")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("z [cm]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def write_plots(run, config, directory: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for exp, title, name in (
        ("nominal_landing", "Exp. 1 nominal landing (trial 1)", "fig3_nominal_landing.png"),
        ("ood_slope", "Exp. 2 OOD slope (trial 1)", "fig5_ood_slope.png"),
    ):
        fig, (ax, zoom) = plt.subplots(1, 2, figsize=(12, 4.5))
        _z_plot(ax, run.logs[exp], title)
        _z_plot(zoom, run.logs[exp], title + ", last seconds")
        zoom.set_xlim(config.landing.descent_end_s - 0.5, config.landing.duration_s)
        zoom.set_ylim(0, 25)
        fig.tight_layout()
        fig.savefig(directory / name, dpi=110)
        plt.close(fig)
        paths.append(directory / name)
    lem = run.logs["lemniscate_near_ground"]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    _z_plot(ax, lem, "Exp. 3 lemniscate near ground (trial 1)")
    fig.tight_layout()
    fig.savefig(directory / "fig6_lemniscate_z.png", dpi=110)
    plt.close(fig)
    paths.append(directory / "fig6_lemniscate_z.png")
    fig, ax = plt.subplots(figsize=(8, 4.5))
    methods = list(run.results["lemniscate_near_ground"]["methods"])
    data = [[v for v in run.results["lemniscate_near_ground"]["methods"][m]["trials"] if v is not None] or [np.nan]
            for m in methods]
    ax.boxplot(data, showmeans=True)
    ax.set_xticks(range(1, len(methods) + 1), methods, rotation=20)
    ax.set_ylabel("z RMSE [cm]")
    ax.set_title("Exp. 3 z-tracking RMSE over trials (paper Fig. 7)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(directory / "fig7_lemniscate_rmse_box.png", dpi=110)
    plt.close(fig)
    paths.append(directory / "fig7_lemniscate_rmse_box.png")
    return paths
