"""The real-flight benchmark on the shipped NanoBench subset (bench/nanobench.py, ~55 s): on the held-out flights the
certified recipe explains more of the z residual than the best linear map inside its bound and than the training
labels' mean, and the neural ESO's composite estimate f_N + Δf̂ (its network trained on the lag-consistent label)
tracks the residual more closely than the ESO alone. The figures are printed with ``-s``."""
from __future__ import annotations

import pytest

from bench.nanobench import (CERTIFIED, COMPOSITE, ESO, LINEAR, MEAN, RESIDUAL, BenchConfig, benchmark, subset_files,
                             summary, table_rows)

pytestmark = pytest.mark.slow  # ~60 s alone: in make test, not make test-fast


def test_certified_recipe_beats_the_linear_map_and_the_mean_and_the_composite_beats_the_eso(tmp_path):
    train, held = subset_files()
    figures = benchmark(train, held, tmp_path, BenchConfig(networks=("a", "a'"), epochs=30))
    print(summary(figures), figures["timings_s"])
    fit, estimate_rows, _, by_height = table_rows(figures)
    for row in (*fit, *by_height, *estimate_rows):
        print("  ".join(row))
    assert figures["data"]["refused"] == [] and len(figures["data"]["heldout_flights"]) == len(held)
    fit, estimate = figures["fit"], figures["estimate"]
    assert fit[RESIDUAL]["slope_pz"] < 0, "the shipped flights show ground effect: the residual falls with height"
    assert fit[CERTIFIED]["r2"] > fit[LINEAR]["r2"] and fit[CERTIFIED]["r2"] > fit[MEAN]["r2"]
    assert estimate[COMPOSITE["a'"]]["rms_mps2"] < estimate[ESO]["rms_mps2"]
    assert estimate[ESO]["samples"] == estimate[COMPOSITE["a'"]]["samples"] > 5000
