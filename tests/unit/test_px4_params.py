"""The one table of PX4 parameters (flight/px4_params.py) and the files made from it: the world's airframe and the
lab table of services/README.md equal what the table makes, and the values issue 30 found wrong in the old README
table are refused."""
from __future__ import annotations

import pytest

from cli.preflight import README, TABLE_BEGIN, TABLE_END, readme_with_table
from flight.px4_params import airframe_text, checked, judge, lab_rows, lab_table, row, rows
from sim.px4_sitl import PARAMS_FILE, load_params


def test_the_airframe_file_is_the_table():
    assert PARAMS_FILE.read_text() == airframe_text(), "run `neso preflight table --write`"


def test_the_readme_lab_table_is_the_table():
    text = README.read_text()
    assert readme_with_table(text, lab_table()) == text, "run `neso preflight table --write`"
    between = text[text.index(TABLE_BEGIN) + len(TABLE_BEGIN):text.index(TABLE_END)]
    assert between.strip() == lab_table().strip()
    for p in lab_rows():
        assert f"| `{p.name}` |" in between


def test_the_world_passes_every_check_it_makes():
    params = {k: float(v) for k, v in load_params().items()}
    for p in checked():
        if not p.required.measured:
            assert judge(p, params[p.name]) == (True, ""), p.name


def test_the_file_carries_each_parameters_type():
    """A float has a point, an int32 none: the MAVLink imitation answers PARAM_VALUE with the right type from it."""
    params = load_params()
    for p in rows():
        if p.world is not None:
            assert ("." in params[p.name]) == (p.kind == "float"), p.name


@pytest.mark.parametrize("name,wrong,fix", [
    ("COM_OBL_RC_ACT", 1, "param set COM_OBL_RC_ACT 5 (Hold mode)"),  # the old table's "1 (hold)": Altitude mode
    ("COM_OBL_RC_ACT", 2, "param set COM_OBL_RC_ACT 5 (Hold mode)"),  # its "2 (land)": Stabilized
    ("COM_OBL_RC_ACT", 0, "param set COM_OBL_RC_ACT 5 (Hold mode)"),  # PX4's default: Position mode
    ("COM_OF_LOSS_T", 0.5, "param set COM_OF_LOSS_T 0.3"),  # the old table's 0.5–1.0 s: measured to end on the floor
    ("COM_OF_LOSS_T", 1.0, "param set COM_OF_LOSS_T 0.3"),
    ("EKF2_EV_QMIN", 0, "param set EKF2_EV_QMIN 1"),  # PX4's default: fuses the pose repeated with quality -1
    ("EKF2_EV_CTRL", 11, "param set EKF2_EV_CTRL 15 (all four bits)"),
    ("EKF2_HGT_REF", 0, "param set EKF2_HGT_REF 3 (Vision)"),
    ("EKF2_GPS_CTRL", 7, "param set EKF2_GPS_CTRL 0"),
    ("NAV_RCL_ACT", 2, "param set NAV_RCL_ACT 3 (Land mode)"),
])
def test_a_wrong_value_is_refused_with_its_fix(name, wrong, fix):
    assert judge(row(name), wrong) == (False, fix)


def test_land_and_hold_both_pass_and_a_missing_parameter_is_named():
    assert judge(row("COM_OBL_RC_ACT"), 4)[0] and judge(row("COM_OBL_RC_ACT"), 5)[0]
    ok, fix = judge(row("EKF2_EV_QMIN"), None)
    assert not ok and "EKF2_EV_QMIN does not exist on this vehicle" in fix


def test_every_checked_row_names_its_px4_source_file():
    for p in rows():
        assert p.source.startswith("src/") and p.why, p.name
        assert p.kind in ("int32", "float")


def test_a_float_as_mavlink_carries_it_still_meets_its_bound():
    import struct

    as_float32 = struct.unpack("<f", struct.pack("<f", 0.3))[0]  # 0.30000001192092896
    assert as_float32 > 0.3 and judge(row("COM_OF_LOSS_T"), as_float32) == (True, "")
    assert not judge(row("COM_OF_LOSS_T"), 0.31)[0]
