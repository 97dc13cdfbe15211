"""How every bench prints its tables and keeps its figures: one ``out/bench.json`` for the whole run."""
from __future__ import annotations

import json
import os

OUT_JSON = os.path.join("out", "bench.json")
RESULTS: dict = {"tables": []}  # this run's figures, written out whole after every change


def write_results(figures: dict | None = None) -> None:
    """Merge ``figures`` (top-level keys, e.g. ``"bus"``) into this run's results and write them out."""
    RESULTS.update(figures or {})
    os.makedirs(os.path.dirname(OUT_JSON), exist_ok=True)
    with open(OUT_JSON, "w") as f:
        json.dump(RESULTS, f, indent=2, ensure_ascii=False)


def print_table(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
    """Left-aligned columns, two spaces apart, a rule under the header; the table also goes to
    ``out/bench.json`` at once, so a run cut short keeps what it measured."""
    widths = [max(len(str(r[i])) for r in (header, *rows)) for i in range(len(header))]
    for row in (header, tuple("-" * w for w in widths), *rows):
        print("  ".join(str(cell).ljust(w) for cell, w in zip(row, widths)).rstrip(), flush=True)
    RESULTS["tables"].append({"columns": list(header), "rows": [[str(c) for c in r] for r in rows]})
    write_results()
