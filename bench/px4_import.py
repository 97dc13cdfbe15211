"""``make bench`` rows: importing PX4 logs (``neso recordings import``), read + write, wall time.

- the shared CubeOrange log (PX4 v1.11, 19.5 min between its first and last timestamp, 0.9 MB; its
  flight data cover only 6.3 s of it);
- a 20-minute log at the SITL log's own logging rates (the shared SITL log's data section tiled 39
  times with its timestamps moved on, real ULog bytes: 57 MB, ~1.15 M messages), which is what a
  lab's 20-minute flight in the default logging profile looks like to the importer.

Target: a 20-minute log under 10 s on these 2 cores. Each row is the best of ``repeats`` runs in one
process (rerun and pyulog already imported by the first); the figures also go to ``out/bench.json``
under ``px4_import``.

    python -m bench.px4_import
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

COLUMNS = ("PX4 log import", "log", "states", "wall s (best)", "target")
TARGET_S = 10.0



def _time_import(path: Path, out_dir: Path, repeats: int) -> tuple[float, int]:
    from recordings.px4_import import import_px4_log

    best, samples = float("inf"), 0
    for _ in range(repeats):
        started = time.perf_counter()
        result = import_px4_log(path, out_dir)
        best = min(best, time.perf_counter() - started)
        samples = len(result.flight)
    return best, samples


def px4_import_rows(quick: bool = False) -> list[tuple[str, ...]]:
    from recordings.px4_import import import_px4_log
    from tests.ulogfiles import CUBE_LOG, SITL_LOG, tiled

    repeats = 1 if quick else 3
    with tempfile.TemporaryDirectory(prefix="neso-bench-px4-") as tmp:
        tmp = Path(tmp)
        import_px4_log(CUBE_LOG, tmp / "warm")  # imports pyulog and rerun once, outside the timing
        cube_s, cube_n = _time_import(CUBE_LOG, tmp, repeats)
        long_log = tmp / "sitl-x39-20min.ulg"
        long_log.write_bytes(tiled(SITL_LOG.read_bytes(), 39))
        long_s, long_n = _time_import(long_log, tmp, repeats)
        long_mb = long_log.stat().st_size / 1e6
    figures = {"cubeorange_19.5min_span_s": round(cube_s, 3), "cubeorange_states": cube_n,
               "sitl_tiled_20min_s": round(long_s, 3), "sitl_tiled_20min_states": long_n,
               "sitl_tiled_20min_mb": round(long_mb, 1), "target_s": TARGET_S}
    _merge_json(figures)
    return [("cubeorange-flight.ulg (v1.11, 19.5 min span, 0.9 MB)", "shared", str(cube_n), f"{cube_s:.2f}",
             f"< {TARGET_S:g} s"),
            (f"20-min log at SITL rates ({long_mb:.0f} MB)", "SITL ×39", str(long_n), f"{long_s:.2f}",
             f"< {TARGET_S:g} s")]


def _merge_json(figures: dict) -> None:
    """Put this section's figures into out/bench.json beside the run's other figures."""
    from bench.table import write_results

    write_results({"px4_import": figures})


if __name__ == "__main__":
    from bench.table import print_table

    print_table(COLUMNS, px4_import_rows())
