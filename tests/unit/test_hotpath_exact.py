"""The per-sample work of the hot path changed how the loop computes, not what: the estimator's and the
controller's outputs over a simulated lemniscate equal, to 1e-12, what the code produced before it
(``tests/data/loop-golden.npz``, made by ``tests/loop_replay.py`` at the commit before; made again, with no
change to the loop's code, when the shipped default network was retrained for issue 29's certificate)."""
from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import REPO
from tests.loop_replay import CASES, fly

GOLDEN = REPO / "tests" / "data" / "loop-golden.npz"


@pytest.mark.parametrize("case", sorted(CASES))
def test_estimates_and_setpoints_equal_the_golden_ones(case):
    golden = np.load(GOLDEN)
    now = fly(*CASES[case])
    for key in ("estimates", "setpoints"):
        expected = golden[f"{case}_{key}"]
        assert now[key].shape == expected.shape
        np.testing.assert_allclose(now[key], expected, rtol=0, atol=1e-12, err_msg=f"{case} {key}")
