"""The dashboard in real headless Chromium against `neso up --secure` (mutual TLS, the graph's ACL):
the page shows the flight, and what the operator does there (pathway, L_N through the
certificate, missions) is answered by the services, because the dashboard presents the
`operator` certificate. The same page, its controls and its refusals as in test_dashboard.py;
this module checks they survive the secure bus.
"""
from __future__ import annotations

import re
import shutil
import tempfile
import threading
import time

import pytest

from runtime.client import get_params
from runtime.probe import Probe
from runtime.schema import Keys
from tests.browser.chromium import (KeptReniced, choose, launch, open_dashboard, set_lipschitz, tab, text, wait_status,
                                    wait_text)
from runtime.launcher import interrupt
from tests.busutil import free_port, neso, secure_init, secure_peer, session

KEYS = Keys("uav1")


class SecureFlight:
    def __init__(self):
        self.workdir = tempfile.mkdtemp(prefix="neso-dashboard-secure-")
        self.dir = secure_init(f"{self.workdir}/secure")
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        self.url = f"http://127.0.0.1:{free_port()}"
        self.proc = neso("up", "--secure", "--secure-dir", self.dir, "--hub", self.endpoint, "--mission", "hover",
                         "--scenario", "nominal_landing", "--dashboard-port", self.url.rsplit(":", 1)[1],
                         "--no-record", "--no-trainer")
        self.output: list[str] = []
        self.pumping = threading.Thread(target=self._pump, daemon=True)
        self.pumping.start()
        self._session_cm = session(secure_peer(self.endpoint, self.dir, "recorder"))  # watches; may not steer
        self.s = self._session_cm.__enter__()
        self.probe = Probe(self.s)

    def _pump(self):
        for line in self.proc.stdout:
            self.output.append(line)

    def close(self) -> str:
        self.probe.close()
        self._session_cm.__exit__(None, None, None)
        try:
            interrupt(self.proc)  # Ctrl-C; the pump thread reads the rest
            self.pumping.join(5.0)
            return "".join(self.output)
        finally:
            shutil.rmtree(self.workdir, ignore_errors=True)


@pytest.fixture(scope="module")
def flight():
    from playwright.sync_api import sync_playwright

    f = SecureFlight()
    try:
        f.probe.wait_for("setpoint", lambda m: m.seq > 50, timeout_s=60)
        with sync_playwright() as pw:
            browser = launch(pw)
            try:
                f.page = open_dashboard(browser, f.url)
                with KeptReniced():
                    yield f
            finally:
                browser.close()
    finally:
        out = f.close()
        print(out[-3000:])


def test_the_page_shows_the_secure_flight(flight):
    t = wait_text(flight.page, r"loop rate\s*\d+\.\d Hz")
    assert "uav1" in t and "pathway" in t and "certificate" in t
    rate = float(re.search(r"loop rate\s*([\d.]+) Hz", text(flight.page)).group(1))
    assert 35.0 < rate < 65.0, rate
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
    set_lipschitz(page, "2.984", override=False)  # base-x2's bound: the estimator refuses it with the margin
    wait_text(page, r"refused · L_N=2\.984 on uav1: certificate FAILS.*margin -")
    set_lipschitz(page, "0.5", override=False)
    wait_text(page, r"accepted · L_N=0\.5 on uav1")
    flight.probe.wait_for("estimate", lambda m: m.network_id.endswith("@L0.5"), timeout_s=5)
    wait_status(page, "certificate", r"^cert HOLDS$")


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
