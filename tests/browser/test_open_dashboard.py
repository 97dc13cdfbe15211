"""The browser tests' ``open_dashboard`` against a dashboard that is not serving yet (as after ``neso up``
starts, or the supervisor's restart of a killed dashboard): it must retry while nothing answers and
then wait for the page, whatever Chromium says about the refused connection (a failed navigation, or
one replaced by its own error page)."""
from __future__ import annotations

import threading
import time

from dashboard.service import Dashboard, DashboardConfig
from runtime.bus import BusConfig
from tests.browser.chromium import launch, open_dashboard, text
from tests.busutil import free_port

LATE_S = 2.0


def test_a_page_opened_before_the_dashboard_serves_shows_it_once_it_does():
    from playwright.sync_api import sync_playwright

    config = DashboardConfig(port=free_port(), nice=0)
    started: list[Dashboard] = []

    def start_late() -> None:
        time.sleep(LATE_S)
        dash = Dashboard(BusConfig(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)), config)
        started.append(dash)
        dash.run()
    threading.Thread(target=start_late, name="late-dashboard", daemon=True).start()
    try:
        with sync_playwright() as pw:
            browser = launch(pw)
            try:
                t0 = time.monotonic()
                page = open_dashboard(browser, f"http://127.0.0.1:{config.port}", timeout_s=40.0)
                waited_s = time.monotonic() - t0
                assert "loop rate" in text(page)
                assert waited_s >= LATE_S * 0.9, waited_s  # it really was not serving when the page was opened
            finally:
                browser.close()
    finally:
        deadline = time.monotonic() + 10.0
        while not started and time.monotonic() < deadline:
            time.sleep(0.1)
        for dash in started:
            dash.stop()
            dash.close()
