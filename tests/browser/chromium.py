"""Debian's Chromium driven by Playwright, as the browser tests and the dashboard bench use it, and the
page helpers the tests share (tabs, dropdowns, waiting for text)."""
from __future__ import annotations

import contextlib
import os
import re
import threading
import time

import pytest

from tests.busutil import timed_step

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--enable-unsafe-swiftshader"]
BROWSER_NICE = 19
#: The shortest time between a page's animation frames (ms): 10 frames a second, the dashboard's own render rate (it
#: sends what changed 10 times a second). viser's page applies what it received once per animation frame, so each
#: update is still applied, at most one period later. Without a GPU, Chromium renders the page's 3D view in software
#: as often as it can: 1.0 core in its GPU process and 0.3 in the page's for 12-16 frames a second at 1600×1000
#: (40-70 ms of CPU a frame at any window size), which starved the flight and the tests beside it
#: (tests/README.md, What the browser paid).
FRAME_PERIOD_MS = 100
#: A page's ``requestAnimationFrame`` callbacks run together once per PERIOD_MS at most (then on the next real frame,
#: so painting stays in step with the compositor); ``cancelAnimationFrame`` as before.
THROTTLE_FRAMES_JS = """(() => {
  const raf = window.requestAnimationFrame.bind(window);
  let queue = new Map(), next = 1, pending = false, last = 0;
  const flush = (t) => { pending = false; last = performance.now(); const q = queue; queue = new Map();
                         q.forEach((cb) => cb(t)); };
  window.requestAnimationFrame = (cb) => {
    const id = next++;
    queue.set(id, cb);
    if (!pending) {
      pending = true;
      setTimeout(() => raf(flush), Math.max(0, PERIOD_MS - (performance.now() - last)));
    }
    return id;
  };
  window.cancelAnimationFrame = (id) => { queue.delete(id); };
})();"""


def launch(pw):
    """A fresh headless Chromium (``pw.chromium.launch``: a new temporary profile each time); a
    clear test failure, not a skip, if Debian's chromium is not installed."""
    if not os.access(CHROMIUM, os.X_OK):
        pytest.fail(f"{CHROMIUM} is missing: install Debian's chromium (apt-get install chromium); "
                    "the dashboard's browser tests need a real browser", pytrace=False)
    return pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)


def new_page(browser, width: int, height: int, frame_period_ms: float | None = FRAME_PERIOD_MS):
    """A page of ``width`` × ``height`` px in ``browser`` whose animation frames come at most every
    ``frame_period_ms`` (None: as often as Chromium renders them, as `make bench` measures the worst case)."""
    page = browser.new_page(viewport={"width": width, "height": height})
    if frame_period_ms is not None:
        page.add_init_script(THROTTLE_FRAMES_JS.replace("PERIOD_MS", f"{frame_period_ms:g}"))
    return page


def _descendants(root: int) -> list[int]:
    parent: dict[int, int] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            with contextlib.suppress(FileNotFoundError, ProcessLookupError, IndexError):  # exited meanwhile
                with open(f"/proc/{d}/stat") as f:
                    parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
    out, frontier = [], [root]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        frontier += kids
    return out


def renice_browsers(nice: int = BROWSER_NICE, cpus: tuple[int, ...] = ()) -> int:
    """Lower the CPU priority of every Chromium process this process started (call after opening
    pages: renderers start with them), and pin it to ``cpus`` if given (``neso up --isolate`` keeps
    the loop off them). On an arena the operator's browser runs on another machine; here it shares
    2 cores with the control loop, and a software-rendered WebGL page would otherwise take them.
    Returns how many processes were reniced."""
    n = 0
    for pid in _descendants(os.getpid()):
        with contextlib.suppress(FileNotFoundError, ProcessLookupError, PermissionError):  # exited meanwhile
            with open(f"/proc/{pid}/comm") as f:
                if "chrom" not in f.read():
                    continue
            for tid in os.listdir(f"/proc/{pid}/task"):  # niceness and affinity are per thread on Linux
                os.setpriority(os.PRIO_PROCESS, int(tid), nice)
                if cpus:
                    os.sched_setaffinity(int(tid), cpus)
            n += 1
    return n


class KeptReniced:
    """``with KeptReniced():`` re-applies :func:`renice_browsers` every ``period_s``: Chromium, run
    as root, lifts some of its threads back to nice −8 and 0 by itself."""

    def __init__(self, period_s: float = 0.25, cpus: tuple[int, ...] = ()) -> None:
        self.period_s, self.cpus = period_s, cpus
        self._done = threading.Event()

    def _run(self) -> None:
        while not self._done.wait(self.period_s):
            renice_browsers(cpus=self.cpus)

    def __enter__(self) -> "KeptReniced":
        renice_browsers(cpus=self.cpus)
        threading.Thread(target=self._run, name="renice-chromium", daemon=True).start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()


class PageWatch:
    """What a page saw besides its DOM, for a failing wait to report: JavaScript errors, and the
    websocket frames from the dashboard (so a frozen page says whether the server stopped sending
    or the page stopped applying)."""

    def __init__(self, page) -> None:
        self.errors: list[str] = []
        self.frames = 0
        self.last_frame_s: float | None = None
        self.sockets: list[str] = []
        page.on("pageerror", lambda exc: self.errors.append(f"pageerror: {exc}"))
        page.on("console", lambda msg: self.errors.append(f"console.{msg.type}: {msg.text}")
                if msg.type == "error" else None)
        page.on("websocket", self._on_socket)

    def _on_socket(self, ws) -> None:
        self.sockets.append(f"open {ws.url}")
        ws.on("framereceived", self._on_frame)
        ws.on("close", lambda _ws: self.sockets.append(f"closed {ws.url} at {time.monotonic():.1f}"))

    def _on_frame(self, _payload) -> None:
        self.frames += 1
        self.last_frame_s = time.monotonic()

    def report(self) -> str:
        last = "never" if self.last_frame_s is None else f"{time.monotonic() - self.last_frame_s:.1f} s ago"
        return (f"[page: {self.frames} websocket frames received, the last {last}; sockets {self.sockets}; "
                f"{len(self.errors)} errors {self.errors[-5:]}]")


def watch_of(page) -> str:
    """The :class:`PageWatch` report of ``page`` ('' for a page opened without one)."""
    w = getattr(page, "_neso_watch", None)
    return w.report() if w is not None else ""


def open_dashboard(browser, url: str, timeout_s: float = 40.0, frame_period_ms: float | None = FRAME_PERIOD_MS):
    """A 1600×1000 page on the dashboard at ``url`` (:func:`new_page`), once it shows its figures (retried while the
    server starts)."""
    from playwright.sync_api import Error as PlaywrightError

    page = new_page(browser, 1600, 1000, frame_period_ms)
    page._neso_watch = PageWatch(page)  # read by watch_of() when a wait fails
    deadline = time.monotonic() + timeout_s

    def left_ms() -> float:
        return max(1.0, (deadline - time.monotonic()) * 1e3)
    # A navigation fails fast while nothing serves (refused, or replaced by Chromium's error page): retried.
    # It is given all the time left, so a starved browser's slow load is never cut short and restarted.
    while True:
        try:
            page.goto(url, wait_until="commit", timeout=left_ms())
            break
        except PlaywrightError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)
    page.get_by_text("loop rate").wait_for(timeout=left_ms())
    return page


@contextlib.contextmanager
def dashboard_page(url: str):
    """Chromium (kept at nice 19 while inside) with one page on the dashboard at ``url``: (browser, page)."""
    from playwright.sync_api import sync_playwright

    driver = sync_playwright()
    pw = driver.__enter__()
    try:
        browser = launch(pw)
        try:
            page = open_dashboard(browser, url)
            with KeptReniced():
                yield browser, page
        finally:
            with timed_step("closing Chromium"):
                browser.close()
    finally:
        with timed_step("stopping Playwright's driver"):
            driver.__exit__(None, None, None)


def text(page) -> str:
    """Everything the page says (its body's text)."""
    return page.evaluate("document.body.textContent")


def tab(page, name: str) -> None:
    page.get_by_role("tab", name=name).click()


def choose(page, label: str, option: str) -> None:
    page.get_by_label(label, exact=True).click()
    page.get_by_role("option", name=option, exact=True).click()


def wait_text(page, pattern: str, timeout_s: float = 10.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        t = text(page)
        if re.search(pattern, t):
            return t
        time.sleep(0.05)
    raise AssertionError(f"{pattern!r} not on the page within {timeout_s} s; page says: {text(page)[-1500:]} "
                         f"{watch_of(page)}")


def loop_rates_until_steady(page, timeout_s: float = 10.0) -> list[float]:
    """The page's loop rate (Hz), read every 0.25 s until it is the loop's 50 Hz within ±10 % or ``timeout_s``
    passed; every reading. The rate is of the last 2 s of setpoint stamps: a moment the machine starved the loop
    shows lower for 2 s (CI, a busy machine: 33.4 Hz; a quiet run's two lanes, the world stood still 0.95 s: 33.3)."""
    rates, deadline = [], time.monotonic() + timeout_s
    while not rates or not 45.0 <= rates[-1] <= 55.0 and time.monotonic() < deadline:
        time.sleep(0.25 if rates else 0.0)
        rates.append(float(re.search(r"loop rate\s*([\d.]+) Hz", text(page)).group(1)))
    return rates


STATUS_JS = """() => Object.fromEntries([...document.querySelectorAll('[data-slot]')]
    .map(e => [e.dataset.slot, e.textContent]))"""
PLOT_POINTS_JS = """() => Object.values((window.__viserTestpoints || {}).uplots || {})
    .map(p => p.chart.data[0].length)"""


def status(page) -> dict[str, str]:
    """The status line: slot → text (source, armed, segment, pathway, network, certificate, recording, link)."""
    return page.evaluate(STATUS_JS)


def wait_status(page, slot: str, pattern: str, timeout_s: float = 10.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = status(page).get(slot, "")
        if re.search(pattern, got):
            return got
        time.sleep(0.05)
    raise AssertionError(f"status {slot} never matched {pattern!r}: {status(page)} {watch_of(page)}")


def hide_notifications(page) -> None:
    """viser's "software WebGL" notice (headless Chromium has no GPU; an operator's browser has one)
    would cover the status line in the screenshots. Hidden by style: a click on a starved page
    can take longer than the notice is worth."""
    page.add_style_tag(content=".mantine-Notification-root { display: none !important; }")


def set_lipschitz(page, value: str, override: bool) -> None:
    """Type ``value`` as the physical L_N, set the override box to ``override``, press Apply L_N."""
    box = page.get_by_label(re.compile(r"^L.N \(physical\)$"))
    box.fill(value)
    box.press("Tab")
    checkbox = page.get_by_label(re.compile(r"Override certificate \(L.N\)"))
    if checkbox.is_checked() != override:
        checkbox.click()
    time.sleep(0.3)  # the number reaches the server before the click
    page.get_by_role("button", name="Apply L_N").click()
