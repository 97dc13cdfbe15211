"""The dashboard in real headless Chromium against `neso up --secure` (mutual TLS, the graph's ACL):
the page shows the flight, and what the operator does there (pathway, L_N through the
certificate, missions) is answered by the services, because the dashboard presents the
`operator` certificate. The same page, its controls and its refusals as in test_dashboard.py;
this module checks they survive the secure bus.
"""
from __future__ import annotations

import tempfile
import time

import pytest

from neso.netfile import load_network
from runtime.client import get_params
from runtime.schema import Keys
from tests.browser.chromium import (choose, dashboard_page, loop_rates_until_steady, set_lipschitz, tab, wait_status,
                                    wait_text)
from tests.busutil import NesoUp, free_port, secure_init, secure_peer
from tests.helpers import REPO

KEYS = Keys("uav1")


class SecureFlight(NesoUp):
    def __init__(self):
        workdir = tempfile.mkdtemp(prefix="neso-dashboard-secure-")
        self.dir = secure_init(f"{workdir}/secure")
        endpoint = f"tls/127.0.0.1:{free_port()}"
        self.url = f"http://127.0.0.1:{free_port()}"
        super().__init__("--secure", "--secure-dir", self.dir, "--hub", endpoint, "--mission", "hover",
                         "--scenario", "nominal_landing", "--dashboard-port", self.url.rsplit(":", 1)[1],
                         "--no-record", "--no-trainer",
                         bus=secure_peer(endpoint, self.dir, "recorder"), workdir=workdir)  # watches; may not steer


@pytest.fixture(scope="module")
def flight():
    f = SecureFlight()
    try:
        f.probe.wait_for("setpoint", lambda m: m.seq > 50, timeout_s=60)
        with dashboard_page(f.url) as (f.browser, f.page):
            yield f
    finally:
        out = f.close()
        print(out[-3000:])


def test_the_page_shows_the_secure_flight(flight):
    t = wait_text(flight.page, r"loop rate\s*\d+\.\d Hz")
    assert "uav1" in t and "pathway" in t and "certificate" in t
    rates = loop_rates_until_steady(flight.page)  # quiet run 29: a stall of the loop showed 33.3 Hz for 2 s
    assert 45.0 <= rates[-1] <= 55.0, rates  # the loop's 50 Hz (before: one reading, anything in 35-65 Hz)
    assert "[hub] Zenoh router" in "".join(flight.output) and "mutual TLS" in "".join(flight.output)


def test_pathway_and_certified_lipschitz_bound_from_the_page_reach_the_estimator(flight):
    page = flight.page
    tab(page, "Control")
    choose(page, "Pathway", "eso")
    wait_text(page, r"accepted · pathway eso")
    flight.probe.wait_for("estimate", lambda m: m.pathway == "eso", timeout_s=5)
    choose(page, "Pathway", "neural_eso")
    wait_text(page, r"accepted · pathway neural_eso")
    flight.probe.wait_for("estimate", lambda m: m.pathway == "neural_eso", timeout_s=5)
    double = load_network(REPO / "networks" / "base-x2.safetensors").lipschitz_bound_physical()
    set_lipschitz(page, f"{double:.4f}", override=False)  # base-x2's bound: the estimator refuses it with the reason
    wait_text(page, rf"refused · L_N={float(f'{double:.4f}'):g} on uav1: certificate FAILS.*fly well")
    set_lipschitz(page, "0.5", override=False)
    wait_text(page, r"accepted · L_N=0\.5 on uav1")
    flight.probe.wait_for("estimate", lambda m: m.network_id.endswith("@L0.5"), timeout_s=5)
    wait_status(page, "certificate", r"^cert HOLDS ≤[\d.]+ cm$")


def test_mission_buttons_fly_the_vehicle_and_the_watching_recorder_identity_reads_but_cannot_steer(flight):
    page = flight.page
    tab(page, "Control")
    page.get_by_role("button", name="Land", exact=True).click()
    wait_text(page, r"accepted · land on uav1")
    flight.probe.wait_for("truth", lambda m: m.on_ground, timeout_s=15)
    page.get_by_role("button", name="Take off", exact=True).click()
    wait_text(page, r"accepted · takeoff on uav1")
    flight.probe.wait_for("truth", lambda m: m.pos_enu_m[2] > 0.8 and not m.on_ground, timeout_s=15)
    from runtime.client import ServiceUnavailable, command

    with pytest.raises(ServiceUnavailable):  # this test's own session is the recorder
        command(flight.s, KEYS, "controller", "land", timeout_s=1.0)
    with pytest.raises(ServiceUnavailable):
        get_params(flight.s, KEYS, "estimator", timeout_s=1.0)
    time.sleep(0.5)
    assert not flight.probe.get("truth")[-1].on_ground
