"""``neso recordings import FILE.ulg``: a PX4 log written as a recording of this system.

The flight read by :func:`recordings.px4.px4_flight` becomes the schema's messages, written by the
recorder's own :class:`recordings.writer.FlightWriter` in the recording layout, so everything that
works on a recording works on it (list, replay, what-if, dataset, train):

- ``state`` (``source="px4"``) at the log's state rate, ``seq`` 0…N−1, ``t_s``/``stamp_s`` in seconds
  since the log started;
- ``setpoint`` (``estimate_source="px4"``) answering each state: PX4's attitude setpoint, the
  normalised thrust over the next period, its newtons and the nominal acceleration ``g + R e₃ T/m``;
- ``telemetry`` at ≤ 10 Hz: armed, in air, flight mode, battery, the hover thrust used;
- ``event/px4``: PX4's own log messages.

Properties: ``import`` (PX4 version, hardware, topics used, hover-thrust source, the mass and whether it
was assumed, rate, gaps, what was skipped), ``flight`` and ``summary`` (``end_reason`` "imported").
No estimates are written: the ESO teacher runs offline over the state and thrust
(:mod:`recordings.teacher`). A refused file writes nothing.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recordings.px4 import ImportConfig, ImportRefused, PX4Flight, px4_flight
from recordings.writer import FlightWriter
from runtime.schema import EventMsg, SetpointMsg, StateMsg, TelemetryMsg, valid_name

TELEMETRY_HZ = 10.0
SERVICE = "px4"  # the events' service name: neso/<v>/event/px4


@dataclass(frozen=True)
class ImportResult:
    path: Path
    flight: PX4Flight
    seconds: float  # wall time of read + write

    def report(self) -> str:
        i = self.flight.info
        lines = [f"imported {i['file_name']} → {self.path}: {i['samples']} samples at {i['state_rate_hz']:.1f} Hz, "
                 f"{i['duration_s']:.1f} s; PX4 {i['px4_version']} on {i['hardware']}; thrust from "
                 f"{i['topics']['thrust']}; hover thrust {i['hover_thrust_source']}; mass {i['mass_kg']:g} kg"
                 + (" (ASSUMED: pass --mass-kg)" if i["mass_assumed"] else "") + f"; {self.seconds:.2f} s"]
        if i["gaps"]["count"]:
            lines.append(f"  {i['gaps']['count']} gaps in the state (longest {i['gaps']['longest_s']:.2f} s): kept as gaps")
        lines += [f"  skipped: {s}" for s in i["skipped"]]
        lines += [f"  note: {n}" for n in i["notes"]]
        return "\n".join(lines)


def flight_messages(flight: PX4Flight, vehicle: str) -> list[tuple[str, object]]:
    """(channel, message) of the whole flight in time order (a state, then the setpoint answering it)."""
    n = len(flight)
    t = flight.t_s.tolist()
    pos, vel = flight.pos_enu_m.tolist(), flight.vel_enu_mps.tolist()
    att, sp, acc = flight.attitude_rad.tolist(), flight.setpoint_rad.tolist(), flight.acc_cmd_enu_mps2.tolist()
    u, thrust_n = flight.thrust_norm.tolist(), flight.thrust_n.tolist()
    every = max(1, int(round(flight.info["state_rate_hz"] / TELEMETRY_HZ)))
    events = sorted(flight.events, key=lambda e: e[0])
    out: list[tuple[str, object]] = []
    e = 0
    for k in range(n):
        while e < len(events) and events[e][0] <= t[k]:
            te, level, text = events[e]
            out.append((f"event/{SERVICE}", EventMsg(stamp_s=max(0.0, te), service=SERVICE, level=level, text=text[:4096])))
            e += 1
        out.append(("state", StateMsg(seq=k, stamp_s=t[k], t_s=t[k], pos_enu_m=tuple(pos[k]), vel_enu_mps=tuple(vel[k]),
                                      roll_rad=att[k][0], pitch_rad=att[k][1], yaw_rad=att[k][2], source="px4")))
        out.append(("setpoint", SetpointMsg(seq=k, stamp_s=t[k], state_stamp_s=t[k], t_s=t[k], roll_rad=sp[k][0],
                                            pitch_rad=sp[k][1], yaw_rad=sp[k][2], thrust_norm=u[k], thrust_n=thrust_n[k],
                                            acc_cmd_enu_mps2=tuple(acc[k]), estimate_source="px4")))
        if k % every == 0:
            out.append(("telemetry", TelemetryMsg(
                stamp_s=t[k], connected=True, armed=bool(flight.armed[k]), in_air=bool(flight.in_air[k]),
                flight_mode=flight.mode[k][:32], roll_rad=att[k][0], pitch_rad=att[k][1], yaw_rad=att[k][2],
                pos_enu_m=tuple(pos[k]), vel_enu_mps=tuple(vel[k]), battery_v=float(flight.battery_v[k]),
                battery_remaining=float(flight.battery_remaining[k]),
                hover_thrust_norm=float(flight.hover_thrust_norm[k]), setpoint_age_s=-1.0, failsafe="")))
    for te, level, text in events[e:]:
        out.append((f"event/{SERVICE}", EventMsg(stamp_s=max(0.0, te), service=SERVICE, level=level, text=text[:4096])))
    return out


def write_flight(flight, path: str | Path, *, vehicle: str, flight_id: str, messages=None, source: str | None = None
                 ) -> Path:
    """Write ``flight`` (its ``info`` is the ``import`` property) to ``path`` through a temporary file beside it
    (nothing is left on failure). ``messages``: (channel, message) in time order (default: a PX4 flight's,
    :func:`flight_messages`); ``source``: the summary's words for where it came from (default: the PX4 log)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.importing.rrd")
    try:
        writer = FlightWriter(tmp, vehicle=vehicle, flight=flight_id, properties={"import": flight.info})
        for channel, msg in (flight_messages(flight, vehicle) if messages is None else messages):
            writer.add(channel, msg)
        writer.set_properties({"summary": {"end_reason": "imported",
                                           "source": source or f"PX4 log {flight.info['file_name']}",
                                           "messages": writer.stats.messages}})
        writer.close()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def import_px4_log(log_path: str | Path, out: str | Path, config: ImportConfig = ImportConfig()) -> ImportResult:
    """Read ``log_path`` and write it as a recording: ``out`` is a folder (``<log name>.rrd`` in it) or
    a ``.rrd`` path. :class:`ImportRefused` (one line, nothing written) for a log that cannot be one."""
    started = time.perf_counter()
    valid_name(config.vehicle, "vehicle")
    out = Path(out)
    target = out if out.suffix == ".rrd" else out / f"{Path(log_path).stem}.rrd"
    flight = px4_flight(log_path, config)
    if not np.all(np.isfinite(flight.thrust_n)) or np.any(flight.thrust_n > 1e4):
        raise ImportRefused(f"{log_path}: thrust in newtons out of range (hover thrust {flight.info['hover_thrust_source']})")
    target.parent.mkdir(parents=True, exist_ok=True)
    stem = Path(log_path).stem
    write_flight(flight, target, vehicle=config.vehicle, flight_id=stem if stem.startswith("px4") else f"px4-{stem}")
    return ImportResult(target, flight, time.perf_counter() - started)
