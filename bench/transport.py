"""Zenoh's transport choices for the loop, side by side (``python -m bench.transport``).

The 500 Hz pipeline (``neso up --isolate``, recorder on) three ways, in rotated rounds so that a
drift of the shared machine falls on every variant alike: Zenoh's defaults (express publishers, the
services' setting); ``--priorities`` (the loop's streams at real-time priority, health, events and
parameter broadcasts at low); ``--low-latency`` (Zenoh's lowlatency unicast transport: no batching,
no QoS). Beside them, once per round, the bare chain with the same three hops
(:func:`bench.hotpath.bare_chain`).
Samples of all rounds are pooled per variant (each round's p99 and misses beside them); ``out/bench.json`` gets them under ``bus.transport``.
"""
from __future__ import annotations

import sys

from bench.hotpath import bare_chain, pipeline, row, summary

COLUMNS = ("transport (500 Hz, --isolate, recorder on)", "samples", "p50 µs", "p99 µs", "max µs", "misses", "notes")
VARIANTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("defaults", ()),
    ("--priorities", ("--priorities",)),
    ("--low-latency", ("--low-latency",)),
)


def _pooled(runs: list[dict]) -> dict:
    """One summary of several runs: percentiles of all their samples together, misses summed."""
    latency = [x for r in runs for x in r["latency_s"]]
    return summary(latency, sum(r["misses"] for r in runs), sum(r["samples"] for r in runs))


def transport_rows(seconds: float, rounds: int, results: dict) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`; ``results["bus"]["transport"]`` gets each variant's pooled summary."""
    runs: dict[str, list[dict]] = {name: [] for name, _ in (("bare chain", ()), *VARIANTS)}
    for k in range(rounds):
        order = VARIANTS[k % len(VARIANTS):] + VARIANTS[:k % len(VARIANTS)]
        runs["bare chain"].append(bare_chain(500.0, seconds, keep_samples=True))
        for name, args in order:
            runs[name].append(pipeline(500.0, seconds, ("--isolate", *args), keep_samples=True))
    out = results.setdefault("bus", {}).setdefault("transport", {})
    rows = []
    for name, variant_runs in runs.items():
        out[name] = s = _pooled(variant_runs)
        s["rounds"] = rounds
        s["p99_us_per_round"] = [r["p99_us"] for r in variant_runs]
        s["misses_per_round"] = [r["misses"] for r in variant_runs]
        per_round = (f"per round p99 {' / '.join(f'{p:.0f}' for p in s['p99_us_per_round'] if p is not None)}, "
                     f"misses {' / '.join(map(str, s['misses_per_round']))}")
        rows.append(row(name, s, ("the floor; " if name == "bare chain" else "") + per_round))
    return rows


def main(argv: list[str]) -> int:
    from bench.table import print_table, write_results

    quick = "--quick" in argv
    results: dict = {}
    print_table(COLUMNS, transport_rows(10.0 if quick else 20.0, 1 if quick else 3, results))
    write_results(results)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
