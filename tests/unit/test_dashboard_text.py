"""The dashboard's text panels, as pure functions of the model (no browser)."""
from __future__ import annotations

import dataclasses

from dashboard.model import FleetModel, certificate_shown
from dashboard.text import (events_markdown, figures_markdown, fmt, health_markdown, network_markdown, predicted_text,
                            vehicle_markdown)
from runtime.schema import EventMsg, NetworkMsg
from tests.helpers import flight_messages


def flown(n: int = 200):
    model = FleetModel(window_s=10.0)
    for topic, msg in flight_messages(n):
        if topic.startswith("health/"):
            model.ingest("uav1", "health", msg, 100.0)
        elif topic.startswith("params/"):
            model.ingest("uav1", "params", msg, 100.0, service=topic.split("/")[1])
        elif topic.startswith("event/"):
            model.ingest("uav1", "event", msg, 100.0)
        else:
            model.ingest("uav1", topic, msg, 100.0 + msg.t_s)
    return model, model.vehicle("uav1")


def test_missing_values_show_as_a_dash():
    assert fmt(float("nan")) == "–" and fmt(None) == "–" and fmt(1.23456, ".2f", " cm") == "1.23 cm"
    model = FleetModel()
    v = model.vehicle("uav2")
    text = figures_markdown(v, 0.0, certificate_shown(v))
    assert "no state yet" in text and "| pathway | – |" in text
    assert network_markdown(v).startswith("**Networks**: no network report on the bus")
    assert "no telemetry on the bus (direct sim)" in vehicle_markdown(v)
    assert "not recorded (no recorder on the bus)" in vehicle_markdown(v)


def test_figures_show_the_newest_sample():
    model, v = flown()
    last = [m for t, m in flight_messages(200) if t == "state"][-1]
    text = figures_markdown(v, 100.0 + last.t_s, certificate_shown(v))
    assert f"**z {last.pos_enu_m[2]:.3f} m**" in text
    assert f"t = {last.t_s:.2f} s" in text
    assert "| pathway | eso |" in text and "`base-L1.0`" in text
    assert "| loop rate | 50.0 Hz |" in text


def test_events_are_grouped_and_health_counts_rejections():
    model, v = flown()
    for _ in range(3):
        model.ingest("uav1", "event", EventMsg(stamp_s=101.0, service="estimator", level="warning", text="late"), 101.0)
    text = events_markdown(v, 104.0)
    assert "`estimator` warning **×3** (3 s ago): late" in text
    model.rejected, model.last_rejection = 2, "state: expected a number, got str"
    health = health_markdown(v, model, 104.0)
    assert "| estimator | " in health and "Dashboard: 2 rejected messages" in health
    assert "(last: state: expected a number, got str)" in health


def test_the_network_panel_shows_the_candidate_and_its_prediction():
    _, v = flown(10)
    candidate = {"id": "uav1-tdr-1", "state": "shadow", "certificate": {"holds": True},
                 "predicted": {"rmse_active_cm": 1.5, "rmse_candidate_cm": 1.2, "change": -0.2}}
    msg = NetworkMsg(stamp_s=100.0, seq=9, active={"id": "base", "source": "file", "feature_set": "state@1"},
                     candidate=candidate, previous={}, shadow_error_rms_mps2=0.05, certificate={},
                     canary={"last": "idle"})
    v.ingest("network", msg, 100.2)
    text = network_markdown(v)
    assert "**Active** `base` from file · inputs state@1" in text
    assert "**Candidate** `uav1-tdr-1` (shadow) · shadow error 0.050 m/s² RMS" in text
    assert predicted_text(candidate) == "predicted z RMSE 1.50 → 1.20 cm (-20 %)" and "certificate holds" in text
    failing = dataclasses.replace(msg, candidate=dict(candidate, certificate={"holds": False}))
    v.ingest("network", failing, 100.3)
    assert "certificate FAILS" in network_markdown(v)
    assert "learned: val loss vs mean not recorded" in network_markdown(v)  # an older file says nothing of it
    learned = dataclasses.replace(msg, candidate=dict(candidate, val_loss_vs_mean=0.41,
                                                      slopes={"pos_z_m": -2.41, "pitch_rad": -0.22}),
                                  shadow_error_rms_mps2=-1.0)
    v.ingest("network", learned, 100.4)
    text = network_markdown(v)
    assert "learned: val loss 0.410 × the mean's · slopes pos_z_m -2.41, pitch_rad -0.22" in text
    assert "shadow error none yet" in text  # no shadow sample yet: no made-up number
    # what it learned, in gain terms, and the prediction against PD+ESO and its slopes flown as gain alone
    split = dict(candidate, gain_change={"dkp": 5.46, "dkd": 1.58}, predicted={
        "rmse_active_cm": 1.5, "rmse_candidate_cm": 1.2, "change": -0.2, "rmse_pdeso_cm": 1.4, "change_vs_pdeso": -1 / 7,
        "rmse_gain_only_cm": 1.25, "gain_only": {"dkp": 5.46, "dkd": 1.58, "kp": 15.46, "kd": 7.58},
        "split": {"total_cm": 0.2, "gain_cm": 0.15, "learned_cm": 0.05}})
    v.ingest("network", dataclasses.replace(msg, candidate=split), 100.5)
    text = network_markdown(v)
    assert "as gain Δk_p +5.46 /s², Δk_d +1.58 /s" in text
    assert ("predicted z RMSE 1.50 → 1.20 cm (-20 %); PD+ESO at the flown gains 1.40 cm (candidate -14 %); its slopes "
            "as gain alone (k_p 15.5, k_d 7.58: Δk_p +5.46, Δk_d +1.58) 1.25 cm: of the 0.20 cm it gains over PD+ESO, "
            "0.15 is gain and 0.05 learned disturbance") in text


def test_the_certificate_row_keeps_its_bound_in_one_cell():
    """The verdict states |e_z| in cm; its pipes are escaped so the figures table keeps two cells per row."""
    from neso.certificate import LoopPlant, NetworkSlopes, flight_certificate
    from neso.control import ControlConfig

    model, v = flown()
    verdict = flight_certificate(NetworkSlopes(1.0), kp=10.0, kd=6.0, omega_o=15.0, plant=LoopPlant.of(ControlConfig()))
    report = dict(verdict.to_dict(), segment="hover", segment_bound_cm=17.2, segment_pdeso_bound_cm=13.3)
    v.ingest("network", NetworkMsg(stamp_s=1.0, seq=1, active={"id": "a"}, candidate={}, previous={},
                                   shadow_error_rms_mps2=-1.0, certificate=report), 0.0)
    shown = certificate_shown(v)
    assert shown.text.startswith("|e_z| ≤ 17.2 cm (PD+ESO 13.3, hover) — certificate holds")
    row = next(line for line in figures_markdown(v, 100.0, shown).splitlines() if line.startswith("| certificate |"))
    cells = [c for c in row.replace("\\|", "").split("|") if c.strip()]
    assert len(cells) == 2 and "\\|e_z\\| ≤ 17.2 cm" in row


def test_the_preflight_verdict_is_shown_as_the_gateway_published_it():
    from runtime.schema import PreflightMsg

    model = FleetModel()
    v = model.vehicle("uav1")
    assert "no verdict on the bus (no px4_gateway)" in vehicle_markdown(v)
    model.ingest("uav1", "preflight", PreflightMsg(stamp_s=1.0, checked_s=1.0, go=False, items={
        "EKF2_EV_QMIN": ["no-go", "0", "param set EKF2_EV_QMIN 1"], "battery": ["go", "90 %", ""],
        "motion capture jitter": ["warning", "270.0 ms (p99 − p50)", "look for Wi-Fi"]}), 1.0)
    text = vehicle_markdown(v)
    assert "**Preflight**: **NO-GO** (3 items, 1 warnings)" in text
    assert "- **NO-GO** EKF2_EV_QMIN: 0 → param set EKF2_EV_QMIN 1" in text
    assert "- warning motion capture jitter: 270.0 ms (p99 − p50) → look for Wi-Fi" in text and "battery" not in text
