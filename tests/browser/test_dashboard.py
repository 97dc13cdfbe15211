"""The dashboard in real headless Chromium against a real `neso up` flight (real time, sim source).

One flight and one browser page are shared by the tests, which run in file order: the page,
a fresh page filled within 2 s (status line, plots, certificate), live updates, pathway, L_N,
missions, the other developers' topics, bus → DOM latency, the screenshots (1600×1000 and
1280×800, out/artifacts/dashboard-<w>x<h>.png), then `kill -9` of the dashboard and its restart.
Figures measured here are written to out/artifacts/dashboard-figures.json.
"""
from __future__ import annotations

import json
import math
import os
import re
import signal
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from neso.netfile import load_network, save_network
from runtime.client import command, get_params
from runtime.schema import EventMsg, Keys, StateMsg, TelemetryMsg
from tests.browser.chromium import (FRAME_PERIOD_MS, PLOT_POINTS_JS, STATUS_JS, choose, dashboard_page, hide_notifications,
                                    loop_rates_until_steady, new_page, open_dashboard, set_lipschitz, status, tab, text,
                                    wait_status, wait_text, watch_of)
from tests.busutil import REPO, NesoUp, children_of, free_port, peer
from tests.helpers import candidate

# the status line, the plots' sample counts and the page's text in one evaluation, with the page's time since its
# load event (ms)
SNAPSHOT_JS = f"""() => ({{status: ({STATUS_JS})(), points: ({PLOT_POINTS_JS})(), text: document.body.textContent,
    after_load_ms: performance.now() - performance.getEntriesByType('navigation')[0].loadEventEnd}})"""

ARTIFACTS = Path(REPO) / "out" / "artifacts"
KEYS = Keys("uav1")
FIGURES: dict[str, object] = {}


class Flight(NesoUp):
    def __init__(self):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.web_port = free_port()
        self.url = f"http://127.0.0.1:{self.web_port}"
        workdir = tempfile.mkdtemp(prefix="neso-dashboard-test-")
        super().__init__("--scenario", "nominal_landing", "--mission", "hover", "--hub", endpoint,
                         "--dashboard-port", str(self.web_port), "--recordings-dir", f"{workdir}/recordings",
                         "--registry", f"{workdir}/registry", bus=peer(endpoint), workdir=workdir)

    def dashboard_pid(self) -> int | None:
        """The pid of the ``neso run dashboard`` under ``neso up``, None while there is none."""
        for pid in children_of(self.proc.pid):
            try:
                cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except FileNotFoundError:  # exited since it was listed
                continue
            if b"dashboard" in cmdline and b"run" in cmdline:
                return pid
        return None


@pytest.fixture(scope="module")
def flight():
    f = Flight()
    try:
        f.probe.wait_for("setpoint", lambda m: m.seq > 50, timeout_s=60)
        with dashboard_page(f.url) as (f.browser, f.page):
            yield f
    finally:
        f.close()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "dashboard-figures.json").write_text(json.dumps(FIGURES, indent=2))
        (ARTIFACTS / "dashboard-neso-up.log").write_text("".join(f.output))


def test_page_loads_and_shows_the_flight(flight):
    page = flight.page
    t = wait_text(page, r"loop rate\s*\d+\.\d Hz")
    assert "uav1" in t and "pathway" in t and "certificate" in t
    wait_text(page, r"Pose \(t = \d+\.\d\d s")
    # the loop's 50 Hz on the page, read until 2 s of it ran at its rate: within ±10 % (before: one reading,
    # anything in 35-65 Hz)
    rates = loop_rates_until_steady(page)
    assert 45.0 <= rates[-1] <= 55.0, rates


def test_the_pages_frames_keep_coming_at_most_one_per_render_period(flight):
    """The harness's frame throttle (tests/browser/chromium.py, FRAME_PERIOD_MS): the page still animates, at most as
    often as the dashboard renders."""
    frames = flight.page.evaluate("""() => new Promise(done => { let n = 0; const t0 = performance.now();
        const frame = () => { n++; if (performance.now() - t0 < 2000) requestAnimationFrame(frame); else done(n); };
        requestAnimationFrame(frame); })""")
    assert 5 <= frames <= 2000 / FRAME_PERIOD_MS + 1, frames


def test_a_fresh_page_shows_status_plots_and_certificate_as_soon_as_it_shows_anything(flight):
    """A page opened mid-flight: the status line (armed/mode, pathway, network, certificate,
    recording), all five plots with samples and the certificate's verdict are there when the page's
    controls first appear, and within 2 s of it; no blank plots, no "computing…". Times from the
    load event; the viser client's own start-up (its script, WebGL in software, Chromium at nice 19
    beside a flight on 2 cores) comes before the controls appear and is reported too."""
    checks = {
        "controls": lambda st, points, page_text: "Vehicle" in page_text and "Live plots" in page_text,
        "status": lambda st, points, page_text: (
            re.fullmatch(r"flying \(sim\)|ARMED.*", st.get("armed", "")) and st.get("pathway") == "neural_eso"
            and st.get("network", "network –") != "network –" and bool(st.get("segment"))
            and re.match(r"● REC \d+ s|not recording", st.get("recording", ""))),
        "certificate": lambda st, points, page_text: (
            re.fullmatch(r"cert (HOLDS|FAILS)( ≤\S+ cm)?", st.get("certificate", ""))
            and re.search(r"certificate (holds|FAILS): state slope", page_text)),
        "plots": lambda st, points, page_text: len(points) == 5 and min(points) >= 10,
    }
    page = new_page(flight.browser, 1280, 800)
    try:
        started = time.monotonic()
        page.goto(flight.url, wait_until="load", timeout=20000)
        loaded = time.monotonic()
        shown: dict[str, float] = {}
        round_trips: list[float] = []
        while len(shown) < len(checks) and time.monotonic() < loaded + 40.0:  # the wait open_dashboard allows
            # one snapshot of the page, timed by its own clock from its load event: a slow round trip to a busy
            # page delays when the test learns of it, not when it was there
            asked = time.monotonic()
            snap = page.evaluate(SNAPSHOT_JS)
            round_trips.append(time.monotonic() - asked)
            for name, check in checks.items():
                if name not in shown and check(snap["status"], snap["points"], snap["text"]):
                    shown[name] = round(snap["after_load_ms"] / 1000.0, 3)
            time.sleep(0.02)
        FIGURES["fresh_page_shown_after_load_s"] = shown
        FIGURES["fresh_page_load_event_after_navigation_s"] = round(loaded - started, 3)
        FIGURES["fresh_page_slowest_snapshot_s"] = round(max(round_trips), 3)
        print("fresh page: shown after its load event (s):", shown, "; load event", round(loaded - started, 3),
              "s after navigation started; slowest snapshot", round(max(round_trips), 3), "s")
        assert set(shown) == set(checks), (status(page), page.evaluate(PLOT_POINTS_JS))
        # filled within 2 s of the page showing anything; how soon it shows (the client's own start-up, Chromium at
        # nice 19 here) is a speed figure, in make bench (bench.dashboard) and dashboard-figures.json, not a bound:
        # it was < 8 s here, and 9.5 s with a core busy and the other worker training (run 15, everything at once)
        assert max(shown.values()) - shown["controls"] < 2.0, shown
        assert status(page)["source"] == "LIVE · sim" and re.fullmatch(r"\d+ Hz( · \d+ miss/min)?", status(page)["link"])
    finally:
        page.close()


def test_altitude_plot_and_pose_update_while_the_sim_flies(flight):
    page = flight.page
    tab(page, "Flight")
    pose = lambda: re.search(r"Pose \(t = ([\d.]+) s.*?z ([\d.]+) m", text(page))
    plot = page.locator("canvas").first  # the altitude uPlot (first panel, first plot)
    before, shot_before = pose(), plot.screenshot()
    time.sleep(2.0)
    after, shot_after = pose(), plot.screenshot()
    assert float(after.group(1)) > float(before.group(1)) + 1.0  # the source clock moved on the page
    assert after.group(0) != before.group(0)
    assert shot_after != shot_before  # the plot was redrawn with new samples
    frames = page.evaluate("document.querySelectorAll('canvas').length")
    assert frames >= 6  # five plots and the 3D scene


CLICK_RECORDER = """
window.__clicks = [];
document.addEventListener('click', () => window.__clicks.push(performance.timeOrigin + performance.now()), true);
"""


def test_pathway_chosen_in_the_ui_is_reported_by_the_estimator(flight):
    """Each pathway chosen on the page flies: the estimator reports it on the bus and the page says accepted. How
    soon is printed, two ways: from the page's click event (the operator's click as the page gets it; wall clock
    shared by browser and test) and from Playwright's click call (adds the time a software-rendered, loaded browser
    takes to deliver injected input); the speed itself is `make bench`'s row (bench/dashboard.py: ~200 ms
    typically), not asserted here."""
    page = flight.page
    tab(page, "Control")
    page.evaluate(CLICK_RECORDER)
    from_event, from_call = [], []
    for pathway in ("eso", "neural_eso"):  # each once, and back to the one the next test expects
        page.get_by_label("Pathway", exact=True).click()
        option = page.get_by_role("option", name=pathway, exact=True)
        option.wait_for()
        time.sleep(0.2)
        with flight.probe.lock:
            n0 = len(flight.probe.messages["estimate"])
        page.evaluate("window.__clicks = []")
        wall_minus_mono = time.time() - time.monotonic()
        t0 = time.monotonic()
        option.click(force=True, no_wait_after=True)
        deadline = t0 + 5.0
        arrived = None
        while arrived is None and time.monotonic() < deadline:
            with flight.probe.lock:
                for msg, t in zip(flight.probe.messages["estimate"][n0:], flight.probe.arrivals["estimate"][n0:]):
                    if msg.pathway == pathway:
                        arrived = t
                        break
            time.sleep(0.002)
        assert arrived is not None, f"estimator never reported {pathway}"
        clicks = page.evaluate("window.__clicks")
        assert clicks, "the page saw no click"
        from_event.append(arrived + wall_minus_mono - clicks[0] / 1e3)
        from_call.append(arrived - t0)
        wait_text(page, rf"accepted · pathway {pathway}")
    FIGURES["pathway_page_click_to_bus_ms"] = [round(x * 1e3, 1) for x in from_event]
    FIGURES["pathway_playwright_click_to_bus_ms"] = [round(x * 1e3, 1) for x in from_call]
    print("pathway: page click event → estimator reports it on the bus (ms):", FIGURES["pathway_page_click_to_bus_ms"])
    print("pathway: Playwright click call → estimator reports it (ms):", FIGURES["pathway_playwright_click_to_bus_ms"])
    assert all(x > 0 for x in from_event), "the estimator reported it after the click, not before"


def test_nn_while_airborne_asks_for_confirmation(flight):
    page = flight.page
    tab(page, "Control")
    choose(page, "Pathway", "nn")
    wait_text(page, r"nn while airborne.*Confirm")
    time.sleep(0.5)
    assert flight.probe.get("estimate")[-1].pathway == "neural_eso"  # nothing sent yet
    page.get_by_role("button", name="Cancel").click()
    wait_text(page, r"refused · pathway nn.*cancelled by the operator")
    choose(page, "Pathway", "neural_eso")
    wait_text(page, r"accepted · pathway neural_eso")


def estimator_bound(flight) -> float:
    return get_params(flight.s, KEYS, "estimator").values["lipschitz_bound"]


def _bound(stem: str) -> float:
    return load_network(os.path.join(REPO, "networks", f"{stem}.safetensors")).lipschitz_bound_physical()


def test_the_page_opens_on_the_estimators_certificate_holding(flight):
    page = flight.page
    wait_status(page, "certificate", r"^cert HOLDS ≤[\d.]+ cm$")  # the eventual |e_z| bound for the segment flown
    tab(page, "Flight")
    wait_text(page, r"\|e_z\| ≤ [\d.]+ cm \(PD\+ESO [\d.]+, \w+\) — certificate holds: state slope [\d.]+ of [\d.]+ "
                    r"\(m/s²\)/unit z certified .*kp 10, kd 6")


def test_lipschitz_bound_certified_is_applied_uncertifiable_refused_unless_overridden(flight):
    """The page sends; the estimator checks the certificate and answers; the page shows the answer."""
    page = flight.page
    tab(page, "Control")
    half, double = _bound("base-x0.5"), _bound("base-x2")
    set_lipschitz(page, f"{half:.4f}", override=False)  # a network trained for it is on disk: certified
    wait_text(page, rf"accepted · L_N={float(f'{half:.4f}'):g} on uav1")
    flight.probe.wait_for("estimate", lambda m: m.network_id.startswith("base-x0.5@"), timeout_s=5)

    set_lipschitz(page, f"{double:.4f}", override=False)  # base-x2: stable, but not certified to fly well
    wait_text(page, rf"refused · L_N={float(f'{double:.4f}'):g} on uav1: certificate FAILS.*fly well")
    time.sleep(0.5)
    assert flight.probe.get("estimate")[-1].network_id.startswith("base-x0.5@")  # nothing changed

    set_lipschitz(page, f"{double:.4f}", override=True)
    wait_text(page, rf"accepted · L_N={float(f'{double:.4f}'):g} on uav1")
    flight.probe.wait_for("estimate", lambda m: m.network_id.startswith("base-x2@"), timeout_s=5)
    wait_status(page, "certificate", r"^cert FAILS")
    set_lipschitz(page, f"{_bound('base'):.6f}", override=False)
    wait_status(page, "certificate", r"^cert HOLDS")


def test_land_and_take_off_buttons_move_the_simulated_vehicle(flight):
    page = flight.page
    tab(page, "Control")
    page.get_by_role("button", name="Land", exact=True).click()
    wait_text(page, r"accepted · land on uav1")
    flight.probe.wait_for("truth", lambda m: m.on_ground, timeout_s=15)
    page.get_by_role("button", name="Take off", exact=True).click()
    wait_text(page, r"accepted · takeoff on uav1")
    flight.probe.wait_for("truth", lambda m: m.pos_enu_m[2] > 0.8 and not m.on_ground, timeout_s=15)


def test_scenario_switch_restarts_the_simulated_world_without_restarting_processes(flight):
    page = flight.page
    tab(page, "Control")
    pids = sorted(children_of(flight.proc.pid))
    choose(page, "Scenario", "slope")
    page.get_by_role("button", name="Restart world with scenario").click()
    wait_text(page, r"accepted · scenario ood_slope on uav1")
    flight.probe.wait_for("truth", lambda m: m.scenario == "ood_slope", timeout_s=5)
    flight.probe.wait_for("setpoint", lambda m: m.seq > 50 and flight.probe.get("truth")[-1].scenario == "ood_slope",
                          timeout_s=10)
    tab(page, "Flight")
    wait_text(page, r"flight 2\)")
    assert sorted(children_of(flight.proc.pid)) == pids  # same processes


def test_vehicle_selector_lists_every_vehicle_on_the_bus(flight):
    page = flight.page
    other = Keys("uav9")
    for k in range(5):
        flight.s.put(other.topic("state"), StateMsg(
            seq=k, stamp_s=time.monotonic(), t_s=0.02 * k, pos_enu_m=(2.0, 1.0, 0.5), vel_enu_mps=(0.0, 0.0, 0.0),
            roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, source="mocap").to_bytes())
    time.sleep(0.5)
    choose(page, "Vehicle", "uav9")
    wait_status(page, "vehicle", r"^uav9$")
    assert status(page)["segment"] == "idle"
    wait_text(page, r"x \+2\.000 y \+1\.000 z 0\.500 m")
    choose(page, "Vehicle", "uav1")
    wait_status(page, "vehicle", r"^uav1$")
    wait_status(page, "segment", r"^(hover|transit|takeoff)$")


def test_px4_recorder_and_network_reports_are_shown_when_present(flight):
    """Telemetry is published from the test (no PX4 gateway on the direct sim path); the recording
    is the real recorder's, and the network panel drives a real candidate through the estimator."""
    page = flight.page
    flying = flight.probe.get("estimate")[-1].network_id  # the network a roll back returns to
    flight.s.put(KEYS.topic("telemetry"), TelemetryMsg(
        stamp_s=time.monotonic(), connected=True, armed=True, in_air=True, flight_mode="OFFBOARD", roll_rad=0.0,
        pitch_rad=0.0, yaw_rad=0.0, pos_enu_m=(0.0, 0.0, 1.0), vel_enu_mps=(0.0, 0.0, 0.0), battery_v=15.2,
        battery_remaining=0.8, hover_thrust_norm=0.5, setpoint_age_s=0.01, failsafe="").to_bytes())
    wait_status(page, "armed", r"^ARMED · OFFBOARD · in air$", timeout_s=3.0)  # the vehicle's word decides
    wait_text(page, r"REC " + re.escape(flight.workdir) + r"/recordings/\S+\.rrd · \d+\.\d s")
    wait_status(page, "recording", r"^● REC \d+ s$")
    tab(page, "Services")
    wait_text(page, r"ARMED · mode OFFBOARD · in air · battery 15\.20 V \(80 %\)")
    tab(page, "Network")
    page.get_by_role("button", name="Promote candidate").click()
    wait_text(page, r"refused · estimator promote on uav1: .*candidate")  # nothing offered yet
    path = os.path.join(flight.workdir, "cand-7.safetensors")
    save_network(path, candidate(seed=7))
    reply = command(flight.s, KEYS, "estimator", "offer", {"path": path}, timeout_s=5.0)
    assert reply.ok, reply.message
    wait_text(page, r"Candidate cand-7 \(shadow\) · shadow error \d+\.\d+ m/s² RMS")
    page.get_by_role("button", name="Promote candidate").click()
    wait_text(page, r"accepted · estimator promote on uav1")
    wait_text(page, r"Active cand-7")
    page.get_by_role("button", name="Roll back").click()
    wait_text(page, r"accepted · estimator rollback on uav1")
    wait_text(page, rf"Active {re.escape(flying)} ")


def test_an_event_on_the_bus_reaches_the_page(flight):
    """Twelve events, each in the page's text (within 5 s); how soon is printed (`make bench`: bus → DOM)."""
    page = flight.page
    tab(page, "Flight")
    samples = []
    for i in range(12):
        marker = f"probe-{i}-{os.getpid()}"
        t0 = time.monotonic()
        flight.s.put(KEYS.event("probe"), EventMsg(stamp_s=t0, service="probe", level="info", text=marker).to_bytes())
        page.wait_for_function("m => document.body.textContent.includes(m)", arg=marker, polling="raf", timeout=5000)
        samples.append(time.monotonic() - t0)
        time.sleep(0.05)
    ms = np.array(samples) * 1e3
    FIGURES["bus_to_dom_ms"] = {"p50": round(float(np.percentile(ms, 50)), 1),
                                "p99": round(float(np.percentile(ms, 99)), 1), "n": len(ms)}
    print("bus → DOM (ms):", FIGURES["bus_to_dom_ms"])


def test_screenshots_at_1600x1000_and_1280x800(flight):
    """What an operator sees, at two window sizes (`out/artifacts/dashboard-<w>x<h>.png`): the
    status line, five plots, the 3D view and the figures, nothing cut off."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for width, height in ((1600, 1000), (1280, 800)):
        page = flight.page if width == 1600 else new_page(flight.browser, width, height)
        try:
            if page is not flight.page:
                page.goto(flight.url, wait_until="load", timeout=20000)
                page.get_by_text("loop rate").wait_for(timeout=40000)  # a fresh page's start-up: not timed here
            tab(page, "Flight")
            hide_notifications(page)
            time.sleep(1.5)
            boxes = page.evaluate("""() => [...document.querySelectorAll('.uplot')].map(e => e.getBoundingClientRect().bottom)""")
            assert len(boxes) == 5 and max(boxes) <= height, f"a plot below the fold at {width}×{height}: {boxes}"
            path = ARTIFACTS / f"dashboard-{width}x{height}.png"
            page.screenshot(path=str(path))
            assert path.stat().st_size > 50_000
        finally:
            if page is not flight.page:
                page.close()


def setpoint_stream(flight, seconds: float) -> tuple[int, float, float]:
    """(samples the controller skipped, its slowest answer to a state in s, the largest gap between setpoints in s)
    over the next ``seconds``. Times are the services' own stamps (one monotonic clock on this machine): when this
    test process is starved its arrivals bunch up, which says nothing about the flight."""
    with flight.probe.lock:
        n0 = len(flight.probe.messages["setpoint"])
    time.sleep(seconds)
    with flight.probe.lock:
        setpoints = flight.probe.messages["setpoint"][n0:]
    seqs = [m.seq for m in setpoints]
    assert len(seqs) > seconds * 25, f"only {len(seqs)} setpoints in {seconds} s"
    answer_s = max(m.stamp_s - m.state_stamp_s for m in setpoints)
    return seqs[-1] - seqs[0] + 1 - len(seqs), answer_s, float(np.max(np.diff([m.stamp_s for m in setpoints])))


def pose_t(page_text: str) -> float:
    """The flight time (s) of the pose the page shows (−inf while it shows none)."""
    shown = re.search(r"Pose \(t = ([\d.]+) s", page_text)
    return float(shown.group(1)) if shown else -math.inf


def test_kill_the_dashboard_mid_flight_the_flight_goes_on_and_a_restart_picks_it_up(flight):
    """The loop never stops: the controller answers every state (none skipped beyond the window before) and each
    within 0.25 s (a period is 20 ms), measured from the state's own stamp. The largest gap between setpoints is a
    figure, not the claim (before, it was: < 0.25 s): it is the source's too when the machine starves the whole loop
    (three runs with one core busy: the largest setpoint gaps, 45-120 ms, were the states' own, one world period
    apart, since the simulated world steps once per state), and it reached 0.45 s (0.10 s before the kill) in a full
    `make test` with one core busy while the supervisor restarted the dashboard. The controller answering a state
    late is what says the kill reached the flight, and this asserts it."""
    pid = flight.dashboard_pid()
    assert pid is not None, "no dashboard process under neso up"
    skipped_before, answer_before, gap_before = setpoint_stream(flight, 3.0)
    killed_at = time.monotonic()
    os.kill(pid, signal.SIGKILL)
    skipped_after, answer_after, gap_after = setpoint_stream(flight, 3.0)
    FIGURES["dashboard_kill"] = {"skipped_samples_3s_before": skipped_before, "skipped_samples_3s_after": skipped_after,
                                 "slowest_answer_ms_before": round(answer_before * 1e3, 1),
                                 "slowest_answer_ms_after": round(answer_after * 1e3, 1),
                                 "max_setpoint_gap_ms_before": round(gap_before * 1e3, 1),
                                 "max_setpoint_gap_ms_after": round(gap_after * 1e3, 1)}
    print("setpoints around kill -9 of the dashboard:", FIGURES["dashboard_kill"])
    assert answer_after < max(0.25, 1.5 * answer_before), (answer_before, answer_after)  # never stopped
    # no worse than the loaded machine already was, within 10 % of the window's 150 samples: the supervisor's
    # restart of the dashboard (at nice 10) runs in these seconds on a machine whose other core may be busy
    assert skipped_after <= max(15, 3 * skipped_before), (skipped_before, skipped_after)
    # the supervisor restarts it; a fresh page shows the same flight going on
    deadline = killed_at + 40
    while flight.dashboard_pid() in (None, pid):
        assert time.monotonic() < deadline, "dashboard not restarted"
        time.sleep(0.2)
    page = open_dashboard(flight.browser, flight.url)
    state_t = flight.probe.get("state")[-1].t_s
    # the flight as it is now, not from the start: the page reaches the newest state there was when it opened. How far
    # behind its first pose was is a figure (with a core busy the restarted dashboard's first pose was 2.2 s old)
    first = shown = pose_t(wait_text(page, r"Pose \(t = \d+\.\d\d s", timeout_s=15))
    deadline = time.monotonic() + 15
    while shown < state_t:
        assert time.monotonic() < deadline, f"the page still shows t = {shown} s; the flight was at {state_t} s when " \
                                            f"it opened {watch_of(page)}"
        time.sleep(0.1)
        shown = pose_t(text(page))
    FIGURES["dashboard_kill"]["restarted_first_pose_behind_s"] = round(state_t - first, 2)
    wait_text(page, r"loop rate\s*[1-9]\d\.\d Hz")
    wait_text(page, r"ω_o\s*15\.0 rad/s")  # parameters asked again from the live services
    page.close()
