"""`make bench`'s certificate rows run against the certificate package as it is (they broke once, unnoticed,
when the package was split by method)."""
from __future__ import annotations

from bench.certificate import GRID_COLUMNS, grid_rows


def test_the_certificate_grid_row_of_the_flown_gains():
    row = grid_rows(kps=(10.0,), kds=(6.0,), omegas=(12.0, 15.0))[1]  # two rows: the second reuses what the first set up
    cells = dict(zip(GRID_COLUMNS, row))
    assert cells["ω_o"] == "15 ← flown"
    assert float(cells["LMI full"]) > float(cells["tight"]) > float(cells["literal"]) > 0
    assert abs(float(cells["roles"]) - 6.942) < 0.01, cells  # with the velocity filter's 20.6 ms lag (7.396 without)
