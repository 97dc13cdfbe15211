"""The dashboard's text panels as pure functions of the model: Markdown/HTML strings, unit-tested
without a browser (tests/unit/test_dashboard_text.py). Values missing or not finite show as ``–``."""
from __future__ import annotations

import html
import math

from dashboard.model import FleetModel, StatusItem, VehicleModel

LEVEL_RGB = {"ok": "#2b8a3e", "info": "#1864ab", "warn": "#e8590c", "bad": "#c92a2a", "off": "#868e96"}
EVENTS_SHOWN = 6


def shadow_text(rms_mps2: float) -> str:
    """The candidate's shadow error; none before its first shadow sample (the estimator reports −1)."""
    return f"{rms_mps2:.3f} m/s² RMS" if rms_mps2 >= 0 else "none yet"


def learned_text(network: dict) -> str:
    """What a network learned, as the trainer recorded it: validation loss against predicting the mean,
    the mean physical slope per input, and those on p_z and v_z as a change of the z gains."""
    from neso.learning import GainChange

    vs = network.get("val_loss_vs_mean")
    slopes = network.get("slopes") or {}
    change = network.get("gain_change")
    vs_part = f"val loss {vs:.3f} × the mean's" if isinstance(vs, (int, float)) else "val loss vs mean not recorded"
    return (vs_part + (" · slopes " + ", ".join(f"{k} {v:+.3g}" for k, v in slopes.items()) if slopes else "")
            + (f" · as gain {GainChange(change['dkp'], change['dkd']).text()}" if change else ""))


def predicted_text(candidate: dict) -> str:
    """The trainer's closed-loop prediction for a candidate, as the network panel shows it: against the active
    network, PD+ESO at the flown gains and the candidate's slopes flown as gain alone."""
    from sim.counterfactual import prediction_text

    return prediction_text(candidate.get("predicted") or {})


def fmt(x: float, spec: str = ".3f", unit: str = "") -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:{spec}}{unit}"


def status_html(vehicle: str, items: list[StatusItem]) -> str:
    """The status line as coloured badges (text escaped: it carries names from the bus)."""
    badges = [f'<span data-slot="vehicle" style="font:700 14px sans-serif;margin-right:4px">{html.escape(vehicle)}</span>']
    for it in items:
        badges.append(f'<span data-slot="{it.slot}" data-level="{it.level}" title="{html.escape(it.detail)}" '
                      f'style="background:{LEVEL_RGB[it.level]};color:#fff;border-radius:4px;padding:1px 6px;'
                      f'margin:2px;display:inline-block;font:600 12.5px sans-serif;white-space:nowrap">'
                      f'{html.escape(it.text)}</span>')
    return f'<div style="line-height:1.6">{"".join(badges)}</div>'


def recording_text(v: VehicleModel) -> str:
    rec = v.latest.get("recording")
    if rec is None:
        return "not recorded (no recorder on the bus)"
    return f"● REC `{rec.path}` · {rec.duration_s:.1f} s" if rec.recording else "recorder idle"


def pose_text(v: VehicleModel) -> str:
    state = v.latest.get("state")
    if state is None:
        return "no state yet"
    return (f"x {state.pos_enu_m[0]:+.3f} y {state.pos_enu_m[1]:+.3f} **z {state.pos_enu_m[2]:.3f} m** · "
            f"roll {math.degrees(state.roll_rad):+.1f}° pitch {math.degrees(state.pitch_rad):+.1f}° "
            f"yaw {math.degrees(state.yaw_rad):+.1f}°")


def cell(text: str) -> str:
    """``text`` for a markdown table cell: its pipes (``|e_z|``) escaped, so they do not split the row."""
    return text.replace("|", "\\|")


def figures_markdown(v: VehicleModel, now_s: float, cert) -> str:
    """Pose, reference and the table of figures (tracking, rate, misses, latency, network, certificate)."""
    state, est, ref, net = (v.latest.get(k) for k in ("state", "estimate", "reference", "network"))
    rms_z, rms_3d = v.tracking_rms_m()
    lat50, lat99 = v.loop_latency_ms()
    bus50, bus99 = v.bus_latency_ms()
    lp, ln = v.lipschitz()
    misses, span = v.per_minute("source", "deadline_misses", now_s)
    falls, _ = v.per_minute("controller", "local_eso_fallbacks", now_s)
    origin = (str(net.active.get("source", "")) if net is not None else
              v.param_notes.get("estimator", "as loaded at start"))
    segment = ref.segment if ref is not None and now_s - v.received.get("reference", -1e9) < 1.0 else "idle"
    return "\n".join([
        f"**Pose** (t = {fmt(state.t_s if state else math.nan, '.2f')} s, flight {v.flights + 1}): {pose_text(v)}",
        f"**Reference z** {fmt(ref.pos_enu_m[2] if ref else math.nan, '.3f', ' m')} · segment {segment}",
        "",
        "| figure | value |", "|---|---|",
        f"| tracking RMS z / 3D ({v.window_s:g} s) | {fmt(rms_z * 100, '.2f')} / {fmt(rms_3d * 100, '.2f')} cm |",
        f"| loop rate | {fmt(v.loop_rate_hz(), '.1f')} Hz |",
        f"| misses / local-ESO (last {span:.0f} s) | {fmt(misses, '.0f')} / {fmt(falls, '.0f')} |",
        f"| loop latency state→setpoint p50/p99 | {fmt(lat50, '.2f')} / {fmt(lat99, '.2f')} ms |",
        f"| bus → dashboard p50/p99 | {fmt(bus50, '.2f')} / {fmt(bus99, '.2f')} ms |",
        f"| pathway | {est.pathway if est else '–'} |",
        f"| network | `{est.network_id if est else '–'}` ({origin[:120]}) |",
        f"| L_N physical / normalised | {fmt(lp, '.4g')} (m/s²)/unit z / {fmt(ln, '.4g')} |",
        f"| ω_o | {fmt(v.omega_o_rps(), '.1f', ' rad/s')} |",
        f"| certificate | {cell(cert.text)} |",
        f"| canary | {(net.canary.get('last') or 'idle') if net is not None else '–'} |",
        f"| recording | {recording_text(v)} |",
    ])


def events_markdown(v: VehicleModel, now_s: float) -> str:
    """The newest events, repeats grouped with their count."""
    events = []
    for g in v.recent_events(EVENTS_SHOWN):
        ago = max(0.0, now_s - g.last_s)
        count = f" **×{g.count}**" if g.count > 1 else ""
        events.append(f"- `{g.service}` {g.level}{count} ({ago:.0f} s ago): {g.text[:220]}")
    return "**Events** (repeats grouped)\n\n" + ("\n".join(events) if events else "_none_")


def health_markdown(v: VehicleModel, model: FleetModel, now_s: float) -> str:
    """One row per service (alive, rate, staleness, rejected, status) and the dashboard's own counts."""
    rows = ["| service | alive | rate | stale | rejected | status |", "|---|---|---|---|---|---|"]
    for name, sh in sorted(v.services.items()):
        h = sh.health
        stale_ms = max(h.staleness_s.values(), default=-1.0) * 1e3 if h else math.nan
        rows.append(f"| {name} | {'yes' if sh.alive else '**NO**'} | {fmt(h.rate_hz if h else math.nan, '.1f')} Hz | "
                    f"{'⚠ ' if sh.stale(now_s) else ''}{fmt(stale_ms, '.0f')} ms | "
                    f"{int(sum(h.rejected.values())) if h else '–'} | {(h.status if h else 'no report')[:100]} |")
    rows.append(f"\nDashboard: {model.rejected} rejected messages, {model.dropped} dropped (inbox full)"
                + (f" (last: {model.last_rejection[:120]})" if model.rejected else ""))
    return "\n".join(rows)


def vehicle_markdown(v: VehicleModel) -> str:
    """PX4's own report (armed, mode, battery, failsafe) and the recorder's."""
    tel, rec = v.latest.get("telemetry"), v.latest.get("recording")
    tel_text = "**Vehicle (PX4)**: no telemetry on the bus (direct sim)" if tel is None else (
        f"**Vehicle (PX4)**: {'ARMED' if tel.armed else 'disarmed'} · mode {tel.flight_mode} · "
        f"{'in air' if tel.in_air else 'on ground'} · battery {tel.battery_v:.2f} V "
        f"({fmt(tel.battery_remaining * 100 if tel.battery_remaining >= 0 else math.nan, '.0f')} %)"
        + (f" · failsafe **{tel.failsafe}**" if tel.failsafe else "")
        + (f" · {tel.autopilot}" if tel.autopilot else "")
        + (f"\n\n**PX4 says**: {tel.status_text}" if tel.status_text else ""))
    rec_line = "**Recording**: " + (recording_text(v) if rec is None else
                                    f"{recording_text(v)} · flight `{rec.flight}` · {rec.size_bytes / 1e6:.1f} MB · "
                                    f"dropped {rec.dropped}")
    return tel_text + "\n\n" + preflight_markdown(v) + "\n\n" + rec_line


def preflight_markdown(v: VehicleModel) -> str:
    """The px4_gateway's preflight verdict as it published it (the gateway decides and refuses to arm on a
    no-go; the page only shows it): GO or NO-GO, then each no-go and warning item with its fix."""
    pre = v.latest.get("preflight")
    if pre is None:
        return "**Preflight**: no verdict on the bus (no px4_gateway)"
    flagged = [(name, e) for name, e in pre.items.items() if e[0] != "go"]
    head = (f"**Preflight**: {'GO' if pre.go else '**NO-GO**'} ({len(pre.items)} items"
            + (f", {sum(e[0] == 'warning' for _, e in flagged)} warnings" if flagged else "") + ")")
    lines = [f"- {'**NO-GO**' if e[0] == 'no-go' else 'warning'} {name}: {e[1][:160]}"
             + (f" → {e[2][:200]}" if e[2] else "") for name, e in flagged]
    if pre.override:
        lines.append(f"- **overridden by the operator**: {pre.override[:200]}")
    return "\n".join([head, *lines])


def network_markdown(v: VehicleModel) -> str:
    """The active network, the candidate in shadow (error, prediction, certificate), the previous one, the canary."""
    net, est = v.latest.get("network"), v.latest.get("estimate")
    if net is None:
        return ("**Networks**: no network report on the bus; active network from estimates: "
                f"`{est.network_id if est else '–'}`")
    lp, ln = v.lipschitz()
    cand = net.candidate
    return (f"**Active** `{net.active.get('id', '?')}` from {net.active.get('source', '?')} · inputs "
            f"{net.active.get('feature_set', '–')} · L_N {fmt(lp, '.4g')} phys / {fmt(ln, '.4g')} normalised  \n"
            + (f"**Candidate** `{cand.get('id')}` ({cand.get('state', '')}) · shadow error "
               f"{shadow_text(net.shadow_error_rms_mps2)} · {predicted_text(cand)} · "
               f"certificate {'holds' if cand.get('certificate', {}).get('holds') else 'FAILS'}  \n"
               f"learned: {learned_text(cand)}"
               if cand else "no candidate")
            + (f"  \nprevious `{net.previous.get('id')}`" if net.previous else "")
            + f"  \ncanary: {net.canary.get('last') or 'idle'}")
