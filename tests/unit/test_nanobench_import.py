"""NanoBench CSVs (the real Crazyflie flights shipped in tests/data/nanobench) → recordings: frames, heights, the
firmware's thrust curve, the motor lead, one thrust scale per import, the stretches written, and the refusals
(never flown, extrapolated onboard columns, a byte-identical copy, a missing column, bad times, no rotation)."""
from __future__ import annotations

import lzma
import math
import shutil

import numpy as np
import pytest

from bench.nanobench import SUBSET, subset_files
from recordings.dataset import load_training_set
from recordings.nanobench import (CRAZYFLIE_21_PLUS, CRAZYFLIE_MASS_KG, NanoBenchConfig, import_nanobench,
                                  nanobench_flight, read_bytes, read_columns, runs)
from recordings.px4 import ImportRefused
from recordings.reader import read_recording
from recordings.replay import WhatIf, what_if

TRAIN, HELD = subset_files()
NEVER_FLEW = SUBSET / "refused" / "B7_oval_slow_rep1.csv.xz"
EXTRAPOLATED = SUBSET / "refused" / "B6_linear_ramp_rep4.csv.xz"


def columns(path):
    return read_columns(path, read_bytes(path)[1])


def write_csv(path, cols: dict[str, np.ndarray]) -> None:
    names = list(cols)
    rows = np.stack([cols[n] for n in names], axis=1)
    body = "\n".join(",".join(f"{v:.9f}" for v in row) for row in rows)
    path.write_bytes(lzma.compress((",".join(names) + "\n" + body + "\n").encode()))


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """Two training flights imported together: (run, recordings read back)."""
    out = tmp_path_factory.mktemp("nanobench")
    run = import_nanobench(TRAIN[:2], out)
    return run, [read_recording(r.path) for r in run.imported]


def test_the_shipped_flights_import_with_what_came_from_where(imported):
    run, recs = imported
    assert run.refused == [] and len(recs) == 2
    for result, rec in zip(run.imported, recs):
        info = rec.properties["import"]
        assert info["format"] == "NanoBench CSV" and info["hardware"] == "Crazyflie 2.1"
        assert info["firmware"] == "2025.12.1" and info["trajectory"] in result.flight.info["file_name"]
        assert info["mass_kg"] == CRAZYFLIE_MASS_KG and "CF_MASS" in info["mass_source"]
        model = info["thrust_model"]
        assert model["coefficients"] == list(CRAZYFLIE_21_PLUS.coefficients) and "2025.12.1" in model["source"]
        assert model["scale"] == run.scale == pytest.approx(np.median([r.flight.own_scale for r in run.imported]))
        assert "median of the 2 flight(s)" in model["scale_source"]
        assert 0.0 <= info["motor_lead_s"] < 0.2
        assert rec.properties["summary"]["end_reason"] == "imported"
        states, setpoints = rec.channel("state").messages(), rec.channel("setpoint").messages()
        assert len(states) == info["samples"] > 1500 and {m.source for m in states} == {"mocap"}
        assert {m.estimate_source for m in setpoints} == {"crazyflie"}
        assert len(rec.channel("telemetry")) > 0 and "Crazyflie firmware 2025.12.1" in \
            rec.channel("telemetry").messages()[0].autopilot


def test_heights_are_above_the_rest_height_and_the_floor_is_left_out(imported):
    run, recs = imported
    for result, rec in zip(run.imported, recs):
        flight = result.flight
        cols = columns(next(p for p in TRAIN if p.name == flight.info["file_name"]))
        first_on = int(np.argmax(np.any(np.stack([cols[f"motor_motor_m{i}"] for i in range(1, 5)]) > 0, axis=0)))
        assert flight.info["rest_height_vicon_m"] == pytest.approx(np.median(cols["pz"][:first_on]))
        z = np.array([m.pos_enu_m[2] for m in rec.channel("state").messages()])
        touches = sum(int(n.split()[0]) for n in flight.notes if "touching the floor" in n)
        assert np.sum(z <= NanoBenchConfig().airborne_height_m) <= touches and z.min() > -0.01 and z.max() > 0.8
        # every stretch written starts with the setpoint of the row before it (the thrust acting into its first sample)
        seq = np.array([m.seq for m in rec.channel("state").messages()])
        sp = {m.seq for m in rec.channel("setpoint").messages()}
        starts = [seq[0]] + [s for a, s in zip(seq[:-1], seq[1:]) if s != a + 1]
        assert all(s - 1 in sp for s in starts) and len(sp) == len(seq) + len(starts)


def test_attitude_thrust_and_the_observers_input_follow_the_stated_model(imported):
    run, recs = imported
    result, rec = run.imported[0], recs[0]
    cols = columns(TRAIN[0])
    state = {m.seq: m for m in rec.channel("state").messages()}
    k = sorted(state)[500]
    qx, qy = cols["qx"][k], cols["qy"][k]
    q = np.array([cols[c][k] for c in ("qx", "qy", "qz", "qw")])
    tilt = (1 - 2 * (qx * qx + qy * qy)) / np.dot(q, q)
    m = state[k]
    assert math.cos(m.roll_rad) * math.cos(m.pitch_rad) == pytest.approx(tilt, abs=1e-6)
    sp = {s.seq: s for s in rec.channel("setpoint").messages()}[k]
    assert sp.thrust_n == pytest.approx(run.scale * result.flight.curve_thrust_n[k])
    assert sp.acc_cmd_enu_mps2[2] == pytest.approx(tilt * sp.thrust_n / CRAZYFLIE_MASS_KG - 9.81, abs=1e-3)


def test_the_curve_is_the_firmwares_inverted_compensation():
    """The firmware's own closed-form inverse (motorsCompensateBatteryVoltage, motors.c) of a thrust gives back a
    motor voltage on which the curve returns that thrust, and voltage_for agrees with it."""
    c0, c1, c2, c3 = CRAZYFLIE_21_PLUS.coefficients
    for thrust in (0.02, 0.05, 0.08, 0.11):
        p = -c2 / (3 * c3)
        q = p ** 3 + (c2 * c1 - 3 * c3 * (c0 - thrust)) / (6 * c3 * c3)
        r = c1 / (3 * c3)
        qrp = math.sqrt(q * q + (r - p * p) ** 3)
        volts = np.cbrt(q + qrp) + np.cbrt(q - qrp) + p
        assert CRAZYFLIE_21_PLUS.thrust_n(volts) == pytest.approx(thrust, abs=1e-9)
        assert CRAZYFLIE_21_PLUS.voltage_for(np.array(thrust)) == pytest.approx(volts, abs=2e-3)


def test_the_motor_lead_follows_the_motor_columns(tmp_path):
    """The same flight with its motor columns moved 50 ms earlier leads by 50 ms more."""
    cols = columns(TRAIN[0])
    shifted = dict(cols)
    for i in range(1, 5):
        shifted[f"motor_motor_m{i}"] = np.append(cols[f"motor_motor_m{i}"][5:], [0.0] * 5)
    write_csv(tmp_path / "shifted.csv.xz", shifted)
    before = nanobench_flight(TRAIN[0]).info["motor_lead_s"]
    after = nanobench_flight(tmp_path / "shifted.csv.xz").info["motor_lead_s"]
    assert after - before == pytest.approx(0.05, abs=0.0101)


def test_one_scale_per_import_and_a_given_one_is_kept(tmp_path):
    own = [nanobench_flight(p).own_scale for p in TRAIN[:3]]
    run = import_nanobench(TRAIN[:3], tmp_path / "a")
    assert run.scale == pytest.approx(np.median(own)) and len(set(own)) == 3
    given = import_nanobench(HELD[:1], tmp_path / "b", NanoBenchConfig(thrust_scale=run.scale))
    info = read_recording(given.imported[0].path).properties["import"]["thrust_model"]
    assert info["scale"] == run.scale and info["scale_source"] == "given" and info["flight_scale"] != run.scale


def test_an_import_trains_and_replays(imported):
    run, recs = imported
    ts = load_training_set([str(r.path) for r in run.imported], "eso")
    assert len(ts) > 3000 and ts.mass_kg == CRAZYFLIE_MASS_KG and np.all(np.isfinite(ts.y_mps2))
    cmp = what_if(recs[0], WhatIf(pathway="neural_eso"))
    assert cmp.against == "ESO offline" and cmp.samples > 1500


@pytest.mark.parametrize("case, needle", [
    ("never flew", "never flew: the motors never ran"),
    ("extrapolated", "motor ratio reaches"),
    ("copy", "byte-identical to"),
    ("no battery", "lacks column(s) pwr_pm_vbat"),
    ("times", "times not increasing"),
    ("quaternion", "attitudes are no rotation"),
    ("missing", "no such file"),
])
def test_bad_files_are_refused_in_one_line_and_nothing_is_written(tmp_path, case, needle):
    good = TRAIN[0]
    if case == "never flew":
        paths = [NEVER_FLEW]
    elif case == "extrapolated":
        paths = [EXTRAPOLATED]
    elif case == "copy":
        shutil.copy(good, tmp_path / "copy.csv.xz")
        paths = [good, tmp_path / "copy.csv.xz"]
    elif case == "no battery":
        cols = columns(good)
        write_csv(tmp_path / "bad.csv.xz", {k: v for k, v in cols.items() if k != "pwr_pm_vbat"})
        paths = [tmp_path / "bad.csv.xz"]
    elif case == "quaternion":
        cols = columns(good)
        for c in ("qx", "qy", "qz", "qw"):
            cols[c] = cols[c].copy()
            cols[c][300] = 0.0
        write_csv(tmp_path / "bad.csv.xz", cols)
        paths = [tmp_path / "bad.csv.xz"]
    elif case == "times":
        cols = columns(good)
        cols["t"] = cols["t"].copy()
        cols["t"][100] = cols["t"][99]
        write_csv(tmp_path / "bad.csv.xz", cols)
        paths = [tmp_path / "bad.csv.xz"]
    else:
        paths = [tmp_path / "none.csv"]
    out = tmp_path / "out"
    run = import_nanobench(paths, out)
    assert len(run.refused) == 1, run.refused
    path, why = run.refused[0]
    assert needle in why and "\n" not in why and why.startswith(str(path))
    written = sorted(out.glob("*.rrd")) if out.exists() else []
    assert written == ([out / f"{good.name[:-len('.csv.xz')]}.rrd"] if case == "copy" else []), written


def test_the_refusals_are_import_refused():
    with pytest.raises(ImportRefused, match="never flew"):
        nanobench_flight(NEVER_FLEW)


def test_runs():
    assert runs(np.array([0, 1, 1, 0, 1], dtype=bool)) == [(1, 3), (4, 5)]
    assert runs(np.zeros(3, dtype=bool)) == []
