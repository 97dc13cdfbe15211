"""A PX4 log imported, replayed onto a real bus (`neso replay --to-bus`) and watched by the real dashboard
in headless Chromium: the page labels it a replay (not live) with its source, and its altitude plot
shows the takeoff (read from the plot's own readout: uPlot's legend at the cursor)."""
from __future__ import annotations

import re
import time
from pathlib import Path

from recordings.px4_import import import_px4_log
from tests.browser.chromium import KeptReniced, launch, open_dashboard, text, wait_text
from tests.busutil import REPO, free_port, hub, neso, stop
from tests.ulogfiles import SITL_LOG

ARTIFACTS = Path(REPO) / "out" / "artifacts"
def altitude_at(page, fraction: float) -> float | None:
    """The altitude plot's own readout (uPlot's legend) with the cursor at ``fraction`` of its width
    (0: the oldest sample shown, 1: now); None where it shows no value."""
    plot = page.locator(".uplot", has_text="Altitude")
    box = plot.locator(".u-over").bounding_box()
    page.mouse.move(box["x"] + fraction * box["width"], box["y"] + 0.5 * box["height"])
    value = plot.locator(".u-legend .u-series").nth(1).locator(".u-value").text_content()
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def takeoff_in_plot(page) -> tuple[float | None, float | None]:
    """(altitude at the plot's left end, at its right end), read one right after the other."""
    return altitude_at(page, 0.01), altitude_at(page, 0.99)


def test_replayed_px4_flight_is_labelled_and_its_altitude_plot_shows_the_takeoff(tmp_path):
    from playwright.sync_api import sync_playwright

    imported = import_px4_log(SITL_LOG, tmp_path).path
    endpoint, web = f"tcp/127.0.0.1:{free_port()}", free_port()
    with hub(endpoint):
        dashboard = neso("run", "dashboard", "--connect", endpoint, "--port", str(web), "--nice", "10")
        replay = None
        try:
            with sync_playwright() as pw:
                browser = launch(pw)
                try:
                    page = open_dashboard(browser, f"http://127.0.0.1:{web}")
                    with KeptReniced():
                        replay = neso("replay", str(imported), "--to-bus", "--speed", "2", "--connect", endpoint)
                        label = wait_text(page, r"REPLAY \(not live\)", 30.0)
                        assert "PX4 log px4-sitl-takeoff-hover.ulg" in label and "PX4_SITL" in label
                        assert str(imported) in label
                        assert "LIVE" not in label.replace("not live", "")
                        # the takeoff: at ×2 it happens ~10 s in; the plot holds the last 10 s of flight time
                        deadline, seen, ends = time.monotonic() + 40.0, False, (None, None)
                        while time.monotonic() < deadline and not seen:
                            ends = takeoff_in_plot(page)
                            seen = None not in ends and ends[0] < 0.3 and ends[1] > 1.5
                            time.sleep(0.2)
                        pose_z = float(re.search(r"Pose \(t = [\d.]+ s.*?z (-?[\d.]+) m", text(page)).group(1))
                        ARTIFACTS.mkdir(parents=True, exist_ok=True)
                        page.screenshot(path=str(ARTIFACTS / "dashboard-replay-px4.png"), full_page=True)
                        assert seen, f"no takeoff in the altitude plot: {ends[0]} m on its left, {ends[1]} m on its right"
                        assert pose_z > 1.0, f"the pose beside the plot says z {pose_z} m"
                        replay.wait(40)
                        wait_text(page, r"replay ended · PX4 log px4-sitl-takeoff-hover\.ulg", 10.0)
                finally:
                    browser.close()
        finally:
            out = stop(replay) if replay is not None else ""
            stop(dashboard)
    assert replay.returncode == 0, out
    assert re.search(r"published (\d+) of \1 messages", out), out
