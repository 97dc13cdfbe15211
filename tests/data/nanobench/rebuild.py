"""Rebuild this folder (the shipped NanoBench subset) from the NanoBench repository.

    python tests/data/nanobench/rebuild.py SOURCE

``SOURCE``: the repository github.com/syediu/nanobench-iros2026 as a bare git directory (what the workplace's
``fetch`` brings: ``/work/.mirror/syediu+nanobench-iros2026/repo``; read with ``git show``), a clone, or its
``datasets/dataset`` folder. Standard library only.

Each flight listed below is taken from ``datasets/dataset/<name>.csv``: every row, only the columns
``neso recordings import`` reads (:data:`COLUMNS`, the cells' text unchanged), written as ``<split>/<name>.csv.xz``;
its ``<name>_metadata.yaml`` is copied unchanged beside it, the repository's ``LICENSE`` to ``LICENSE``, and
``MANIFEST.tsv`` lists what was taken (split, file, the source file's SHA-256, rows, bytes written).
"""
from __future__ import annotations

import csv
import hashlib
import io
import lzma
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
COLUMNS = ("t", "px", "py", "pz", "qx", "qy", "qz", "qw", "vx", "vy", "vz", "motor_motor_m1", "motor_motor_m2",
           "motor_motor_m3", "motor_motor_m4", "pwr_pm_vbat")
# Pairs of repetitions of the same trajectories: the held-out flights are new flights of kinds the training flights
# have (another battery, another day), not new trajectory shapes. ``refused``: real files the import must refuse.
SPLITS = {
    "train": ("B9_trefoil_slow_rep1", "B9_trefoil_slow_rep12", "B9_trefoil_slow_rep16", "B9_trefoil_fast_rep1",
              "B2_circle_slow_rep1", "B2_circle_medium_rep1", "B3_figure8_slow_rep1", "B3_figure8_fast_rep1",
              "B6_linear_ramp_rep2"),
    "heldout": ("B9_trefoil_slow_rep15", "B2_circle_slow_rep2", "B3_figure8_medium_rep1", "B6_linear_ramp_rep3"),
    "refused": ("B7_oval_slow_rep1", "B6_linear_ramp_rep4"),
}
DATASET_DIR = "datasets/dataset"


class Source:
    """Files of the NanoBench repository by their path in it (a bare git directory, a clone, or the CSV folder)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.git = (root / "HEAD").is_file() and (root / "objects").is_dir()

    def read(self, rel: str) -> bytes:
        if self.git:
            return subprocess.run(["git", "--git-dir", str(self.root), "show", f"HEAD:{rel}"], check=True,
                                  capture_output=True).stdout
        for base in (self.root, self.root.parent.parent):
            if (base / rel).is_file():
                return (base / rel).read_bytes()
        return (self.root / Path(rel).name).read_bytes()

    def commit(self) -> str:
        if not self.git:
            return "unknown (not a git directory)"
        return subprocess.run(["git", "--git-dir", str(self.root), "rev-parse", "HEAD"], check=True,
                              capture_output=True, text=True).stdout.strip()


def columns_only(data: bytes) -> tuple[bytes, int]:
    """The CSV with only :data:`COLUMNS` (cells unchanged), and its number of data rows."""
    rows = list(csv.reader(io.StringIO(data.decode("utf-8"))))
    index = [rows[0].index(c) for c in COLUMNS]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    for row in rows:
        if row:
            writer.writerow([row[i] for i in index])
    return out.getvalue().encode("utf-8"), len(rows) - 1


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__.strip().splitlines()[2].strip())
        return 2
    source = Source(Path(argv[0]))
    (HERE / "LICENSE").write_bytes(source.read("LICENSE"))
    manifest = [f"# NanoBench subset from github.com/syediu/nanobench-iros2026 at {source.commit()}",
                "split\tfile\tsource\tsource_sha256\trows\tbytes"]
    for split, names in SPLITS.items():
        folder = HERE / split
        folder.mkdir(exist_ok=True)
        for stale in folder.iterdir():
            stale.unlink()
        for name in names:
            original = source.read(f"{DATASET_DIR}/{name}.csv")
            text, rows = columns_only(original)
            packed = lzma.compress(text, preset=9 | lzma.PRESET_EXTREME)
            (folder / f"{name}.csv.xz").write_bytes(packed)
            (folder / f"{name}_metadata.yaml").write_bytes(source.read(f"{DATASET_DIR}/{name}_metadata.yaml"))
            manifest.append(f"{split}\t{name}.csv.xz\t{DATASET_DIR}/{name}.csv\t{hashlib.sha256(original).hexdigest()}\t"
                            f"{rows}\t{len(packed)}")
            print(f"{split}/{name}.csv.xz: {rows} rows, {len(packed) / 1e3:.0f} kB")
    (HERE / "MANIFEST.tsv").write_text("\n".join(manifest) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
