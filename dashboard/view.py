"""The viser page: a status line always in view, the followed vehicle in 3D, live plots, figures,
health and controls.

Layout: the status line (:func:`dashboard.model.status_line`, colour-coded) floats at the top of the
3D view, which follows the vehicle (:mod:`dashboard.scene`); the plots (altitude, z error,
disturbance, thrust, attitude; pause, drag to zoom, double-click to reset) are docked left, the
figures, events, health and controls right. The view reads the model (under the service's model
lock) and renders at a throttled rate; controls only hand a request to the bus facade
(:class:`dashboard.service.BusFacade`), which runs it on a worker thread and reports the reply back
here. Nothing in a UI callback blocks.
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from dashboard.model import FleetModel, VehicleModel, certificate_shown, status_line
from dashboard.provenance import provenance_line
from dashboard.scene import Scene
from dashboard.text import (events_markdown, figures_markdown, health_markdown, network_markdown, status_html,
                            vehicle_markdown)
from flight.controller import CONTROLLER_GAINS
from neso.types import OMEGA_O_RPS, PATHWAYS

RISKY_PATHWAYS = ("nn", "none")  # no online correction: confirm while airborne
MISSIONS = (("Arm", "arm", None), ("Take off", "takeoff", None), ("Hover", "hover", None),
            ("Landing test", "landing_test", None), ("Lemniscate", "lemniscate", None), ("Land", "land", None),
            ("Hold", "hold", "yellow"), ("ABORT", "abort", "red"))
PX4_COMMANDS = (("PX4 arm", "arm", None), ("PX4 offboard", "offboard_start", None), ("PX4 hold", "hold", "yellow"),
                ("PX4 land", "land", None), ("PX4 disarm", "disarm", None))  # px4_gateway (--vehicle mavlink)
SCENARIOS = {"nominal": "nominal_landing", "slope": "ood_slope", "turbulence": "lemniscate_near_ground"}
PLOT_POINTS = 300  # points per series sent to the browser
PLOTS_WIDTH_PX = 470  # left column; the right one is viser's "medium" control width
PLOT_HEIGHT_PX = 106  # five plots and their legends fit an 800 px high window without scrolling
STATUS_WIDTH_PX = 360  # the floating status line fits the 3D view of a 1280 px wide window


def _decimate(columns: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    length = len(next(iter(columns.values())))
    if length <= n:
        return columns
    idx = np.linspace(0, length - 1, n).astype(int)
    return {k: v[idx] for k, v in columns.items()}


def _ffill(a: np.ndarray) -> np.ndarray:
    """NaNs replaced by the previous finite value (leading NaNs by the first finite one, or 0)."""
    a = np.asarray(a, dtype=float).copy()
    ok = np.isfinite(a)
    if not ok.any():
        return np.zeros_like(a)
    idx = np.where(ok, np.arange(len(a)), 0)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.argmax(ok))
    idx[:first] = first
    return a[idx]


def _series(label: str, stroke: str, width: float = 1.5, dash: list | None = None) -> dict:
    out = {"label": label, "stroke": stroke, "width": width}
    if dash:
        out["dash"] = dash
    return out


class DashboardView:
    """Builds the page once and re-renders the selected vehicle on :meth:`render`."""

    def __init__(self, server, model: FleetModel, lock: threading.Lock, bus, *, default_vehicle: str = "uav1") -> None:
        self.server, self.model, self.lock, self.bus = server, model, lock, bus
        self.selected = default_vehicle
        self._text_cache: dict[int, str] = {}
        self._pending_pathway: tuple[str, str] | None = None
        self._build()

    # -- page ------------------------------------------------------------------------------
    def _build(self) -> None:
        gui = self.server.gui
        self.scene = Scene(self.server)
        gui.configure_theme(control_width="medium", show_share_button=False, brand_color=(30, 90, 160))
        gui.main_panel.dock_right()

        status = gui.add_panel()
        with status.add_tab("Status"):
            self.status = gui.add_html(status_html(self.selected, []))
        status.float(x=-6, y=6, width=STATUS_WIDTH_PX)  # top right: viser's notices appear top left
        self.provenance = gui.add_markdown("")  # live, or a replay and of what (dashboard/provenance.py)

        self.vehicle_dd = gui.add_dropdown("Vehicle", (self.selected,), initial_value=self.selected)
        self.vehicle_dd.on_update(lambda _: self._select(self.vehicle_dd.value))
        tabs = gui.add_tab_group()
        with tabs.add_tab("Flight"):
            self.figures = gui.add_markdown("")
            self.events = gui.add_markdown("")
        with tabs.add_tab("Control"):
            self._build_controls(gui)
        with tabs.add_tab("Services"):
            self.health = gui.add_markdown("")
            self.vehicle_status = gui.add_markdown("")
        with tabs.add_tab("Network"):
            self.network = gui.add_markdown("")
            self.net_reply = gui.add_markdown("")
            for label, service, name in (("Train", "trainer", "train"), ("Promote candidate", "estimator", "promote"),
                                         ("Roll back", "estimator", "rollback")):
                gui.add_button(label).on_click(lambda _, s=service, n=name: self._network_cmd(s, n))
        plots = gui.add_panel()
        with plots.add_tab("Live plots"):
            self._build_plots(gui)
        plots.dock_left()
        plots.set_width(PLOTS_WIDTH_PX)
        self.server.on_client_connect(lambda client: client.camera.on_update(lambda _: self._on_camera(client)))

    def _build_controls(self, gui) -> None:
        """Pathway (with a confirmation for the risky ones), L_N, missions, PX4, scenario, gains."""
        self.reply = gui.add_markdown("_no action yet_")
        self.pathway_dd = gui.add_dropdown("Pathway", PATHWAYS, initial_value="neural_eso")
        self.pathway_dd.on_update(self._on_pathway)
        self.confirm_text = gui.add_markdown("", visible=False)
        self.confirm_btn = gui.add_button("Confirm pathway switch", color="red", visible=False)
        self.cancel_btn = gui.add_button("Cancel", visible=False)
        self.confirm_btn.on_click(lambda _: self._confirm_pathway(True))
        self.cancel_btn.on_click(lambda _: self._confirm_pathway(False))
        self.lip_in = gui.add_number("L_N (physical)", 0.5, min=1e-4, max=100.0, step=1e-4)
        self.lip_override = gui.add_checkbox("Override certificate (L_N)", False)
        self.lip_btn = gui.add_button("Apply L_N")
        self.lip_btn.on_click(lambda _: self._apply_lipschitz())
        with gui.add_folder("Mission"):
            for label, name, color in MISSIONS:
                b = gui.add_button(label, color=color)
                b.on_click(lambda _, name=name: self._mission(name))
        with gui.add_folder("PX4 vehicle (gateway)", expand_by_default=False):
            for label, name, color in PX4_COMMANDS:
                b = gui.add_button(label, color=color)
                b.on_click(lambda _, name=name: self._px4(name))
        with gui.add_folder("Scenario (simulator)"):
            self.scenario_dd = gui.add_dropdown("Scenario", tuple(SCENARIOS), initial_value="nominal")
            gui.add_button("Restart world with scenario").on_click(lambda _: self._scenario())
        with gui.add_folder("Advanced: gains", expand_by_default=False):
            self.gain_in = {p.name: gui.add_number(p.name, p.default, min=p.lo, max=p.hi, step=0.1)
                            for p in CONTROLLER_GAINS}
            self.omega_in = gui.add_number("ω_o rad/s (start-up, read-only)", OMEGA_O_RPS, disabled=True)
            self.gain_override = gui.add_checkbox("Override certificate (gains)", False)
            gui.add_button("Apply gains").on_click(lambda _: self._apply_gains())

    def _build_plots(self, gui) -> None:
        """Pause, then five time plots: altitude, z error, the disturbance's parts, thrust, attitude."""
        self.pause = gui.add_checkbox("Pause plots", False, hint="freeze the plots (the flight goes on); "
                                      "drag across a plot to zoom in time, double-click to zoom out")
        self.paused_note = gui.add_markdown("", visible=False)
        x_scale = {"x": {"time": False}}
        axes = ({"size": 22, "ticks": {"size": 4}}, {"size": 44})

        def plot(title: str, *series: dict):
            """No title row: the plot is named in its legend, so five fit. With up to two series the
            legend shows values on hover (the name rides on x: its value is the time); with more, names
            only (values would wrap it to two lines), the name on the first series."""
            live = len(series) <= 2
            if not live:
                series = ({**series[0], "label": f"{title}: {series[0]['label']}"},) + series[1:]
            return gui.add_uplot((np.zeros(2),) * (len(series) + 1),
                                 ({"label": f"{title} · t (s)" if live else "t (s)"},) + series,
                                 scales=x_scale, axes=axes, height=PLOT_HEIGHT_PX, padding=(8, 12, 0, 0),
                                 legend={"live": live})

        self.alt_plot = plot("Altitude (m)", _series("z", "#1f6fd0", 2), _series("z ref", "#f08c14", 2, [6, 4]))
        self.err_plot = plot("z tracking error (cm)", _series("z − ref", "#d03030", 2))
        self.dist_plot = plot("Disturbance z (m/s²)", _series("f_N", "#8e44ad"), _series("Δf̂", "#27ae60"),
                              _series("f̂", "#2c3e50", 2), _series("truth", "#aaaaaa", 1, [3, 3]))
        self.thrust_plot = plot("Thrust (N)", _series("thrust", "#16a085", 2))
        self.att_plot = plot("Attitude (°)", _series("roll", "#c2255c"),
                             _series("roll setpoint", "#c2255c", 1, [5, 3]), _series("pitch", "#1c7ed6"),
                             _series("pitch setpoint", "#1c7ed6", 1, [5, 3]))

    def _on_camera(self, client) -> None:
        """A page reported its camera: frame it on the vehicle (once)."""
        with self.lock:
            self.scene.frame(client)

    # -- helpers ---------------------------------------------------------------------------
    def _set(self, handle, text: str) -> None:
        """Send text only when it changed (the browser is not re-sent identical text)."""
        if self._text_cache.get(id(handle)) != text:
            self._text_cache[id(handle)] = text
            handle.content = text

    def _show_reply(self, target, what: str, ok: bool, text: str) -> None:
        mark = "✔ **accepted**" if ok else "✖ **refused**"
        self._set(target, f"{mark} · {what}: {text}" if text else f"{mark} · {what}")

    def _vehicle(self) -> VehicleModel:
        return self.model.vehicle(self.selected)

    def _select(self, name: str) -> None:
        self.selected = name

    # -- controls (each only hands a request to the bus facade) ---------------------------
    def _on_pathway(self, _event) -> None:
        value, vehicle = self.pathway_dd.value, self.selected
        with self.lock:
            airborne = self._vehicle().airborne(time.monotonic())
        if value in RISKY_PATHWAYS and airborne:
            self._pending_pathway = (vehicle, value)
            self._set(self.confirm_text, f"⚠ **{value}** while airborne: no online correction of the network. Confirm?")
            for h in (self.confirm_text, self.confirm_btn, self.cancel_btn):
                h.visible = True
            return
        self._send_pathway(vehicle, value)

    def _confirm_pathway(self, yes: bool) -> None:
        pending, self._pending_pathway = self._pending_pathway, None
        for h in (self.confirm_text, self.confirm_btn, self.cancel_btn):
            h.visible = False
        if pending is None:
            return
        if yes:
            self._send_pathway(*pending)
        else:
            self._show_reply(self.reply, f"pathway {pending[1]}", False, "cancelled by the operator")

    def _send_pathway(self, vehicle: str, value: str) -> None:
        self.bus.set_params(vehicle, "estimator", {"pathway": value},
                            lambda ok, text: self._show_reply(self.reply, f"pathway {value} on {vehicle}", ok, text))

    def _apply_lipschitz(self) -> None:
        """The estimator checks the certificate and answers; the page only shows the answer."""
        value, vehicle = float(self.lip_in.value), self.selected
        values = {"lipschitz_bound": value, "override": bool(self.lip_override.value)}
        self.bus.set_params(vehicle, "estimator", values,
                            lambda ok, text: self._show_reply(self.reply, f"L_N={value:g} on {vehicle}", ok, text))

    def _apply_gains(self) -> None:
        """The controller checks the certificate and answers; the page only shows the answer."""
        gains = {k: float(h.value) for k, h in self.gain_in.items()}
        vehicle = self.selected
        self.bus.set_params(vehicle, "controller", {**gains, "override": bool(self.gain_override.value)},
                            lambda ok, text: self._show_reply(self.reply, f"gains {gains} on {vehicle}", ok, text))

    def _mission(self, name: str) -> None:
        vehicle = self.selected
        self.bus.command(vehicle, "controller", name, {},
                         lambda ok, text: self._show_reply(self.reply, f"{name} on {vehicle}", ok, text))

    def _px4(self, name: str) -> None:
        vehicle = self.selected
        self.bus.command(vehicle, "px4_gateway", name, {},
                         lambda ok, text: self._show_reply(self.reply, f"PX4 {name} on {vehicle}", ok, text))

    def _scenario(self) -> None:
        vehicle, name = self.selected, SCENARIOS[self.scenario_dd.value]
        self.bus.command(vehicle, "source", "scenario", {"name": name},
                         lambda ok, text: self._show_reply(self.reply, f"scenario {name} on {vehicle}", ok, text))

    def _network_cmd(self, service: str, name: str) -> None:
        vehicle = self.selected
        self.bus.command(vehicle, service, name, {},
                         lambda ok, text: self._show_reply(self.net_reply, f"{service} {name} on {vehicle}", ok, text))

    # -- rendering -------------------------------------------------------------------------
    def render_pose(self) -> None:
        """Vehicle pose, trail, reference, camera (cheap; called at the fast UI rate)."""
        v = self._vehicle()
        state = v.latest.get("state")
        if state is None:
            return
        ref = v.latest.get("reference")
        fresh_ref = ref if ref is not None and time.monotonic() - v.received.get("reference", -1e9) < 1.0 else None
        self.scene.update(state, v.trail, v.ref_trail, fresh_ref)

    def render(self, now_s: float) -> None:
        """Status, plots, figures and panels of the selected vehicle (called at the slow UI rate)."""
        names = sorted(self.model.vehicles) or [self.selected]
        if tuple(self.vehicle_dd.options) != tuple(names):
            self.vehicle_dd.options = tuple(names)
        if self.selected not in self.model.vehicles and self.model.vehicles:
            self.selected = names[0]
        v = self._vehicle()
        truth = v.latest.get("truth")
        self.scene.show_scenario(truth.scenario if truth is not None else "")
        cert = certificate_shown(v)
        self._set(self.status, status_html(v.name, status_line(v, now_s, cert, dashboard_dropped=self.model.dropped)))
        self._render_plots(v)
        self._render_text(v, now_s, cert)

    def _render_plots(self, v: VehicleModel) -> None:
        paused = bool(self.pause.value)
        if paused != self.paused_note.visible:
            self.paused_note.visible = paused
        if paused:
            state = v.latest.get("state")
            self._set(self.paused_note, "⏸ **plots paused** — the flight goes on" +
                      (f" (now t = {state.t_s:.1f} s)" if state is not None else ""))
            return
        w = v.window()
        if len(w["t"]) < 2:
            return
        w = _decimate(w, PLOT_POINTS)
        t = w["t"] - w["t"][-1]  # seconds before now
        self.alt_plot.data = (t, _ffill(w["z"]), _ffill(w["ref_z"]))
        err = np.where(np.isfinite(w["z"]) & np.isfinite(w["ref_z"]), (w["z"] - w["ref_z"]) * 100.0, np.nan)
        self.err_plot.data = (t, _ffill(err))
        self.dist_plot.data = (t, _ffill(w["f_n_z"]), _ffill(w["df_hat_z"]), _ffill(w["f_hat_z"]),
                               _ffill(w["truth_dist_z"]))
        self.thrust_plot.data = (t, _ffill(w["thrust_n"]))
        deg = 180.0 / math.pi
        self.att_plot.data = (t, _ffill(w["roll"]) * deg, _ffill(w["roll_sp"]) * deg, _ffill(w["pitch"]) * deg,
                              _ffill(w["pitch_sp"]) * deg)

    def _render_text(self, v: VehicleModel, now_s: float, cert) -> None:
        self._set(self.provenance, provenance_line(v, now_s))
        self._set(self.figures, figures_markdown(v, now_s, cert))
        self._set(self.events, events_markdown(v, now_s))
        self._set(self.health, health_markdown(v, self.model, now_s))
        self._set(self.vehicle_status, vehicle_markdown(v))
        self._set(self.network, network_markdown(v))
        if self._pending_pathway is not None and self._pending_pathway[0] != self.selected:
            self._confirm_pathway(False)
