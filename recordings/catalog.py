"""The flights in a recordings folder: one row per ``.rrd`` (``neso recordings list``)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recordings.reader import RecordingError, read_recording


@dataclass(frozen=True)
class Entry:
    path: str
    flight: str
    segment: int
    vehicle: str
    scenario: str
    duration_s: float
    pathways: tuple[str, ...]  # in the order they were flown
    networks: tuple[str, ...]
    lipschitz_bounds: tuple[float, ...]
    samples: int
    size_bytes: int
    closed: str  # why the segment ended ("" if the recorder died while writing it)
    error: str = ""  # why the file could not be read ("" if it could)
    source: str = ""  # where the states came from: sim, mocap, or the PX4 log / NanoBench CSV imported


def _in_order(values) -> tuple:
    out = []
    for v in values:
        if not out or out[-1] != v:
            out.append(v)
    return tuple(dict.fromkeys(out)) if len(out) > 8 else tuple(out)


def source_of(rec, vehicle: str) -> str:
    """Where a recording's states came from, in a few words: the source's own description (its read-only
    parameters, recorded at the flight's start: NatNet version, server and rigid body; the simulated world and how
    it was flown) and the autopilot that flew it (its telemetry: PX4's version); recordings from before the
    description say the states' ``source`` field."""
    imported = rec.properties.get("import")
    if isinstance(imported, dict) and imported.get("format") == "NanoBench CSV":
        return f"NanoBench {imported.get('file_name', '?')} ({imported.get('hardware', '?')}, Vicon)"
    if isinstance(imported, dict):
        version = str(imported.get("px4_version", "?")).split(" ")[0]
        return f"PX4 log {imported.get('file_name', '?')} ({version}, {imported.get('hardware', '?')})"
    d = rec.properties.get("params", {}).get("source")
    autopilots = _autopilots(rec, vehicle)
    flown = f" · {'/'.join(autopilots)}" if autopilots else ""
    if not isinstance(d, dict) or "kind" not in d:
        sources = rec.channel("state", vehicle).columns.get("source", [])
        return ("/".join(dict.fromkeys(sources)) or "-") + flown
    if d["kind"] == "natnet":
        simulated = f", simulated ({d['scenario']})" if d.get("world") else ""
        return (f"NatNet {'.'.join(str(d.get('natnet_version', '?')).split('.')[:2])} {d.get('rigid_body', '?')}@"
                f"{d.get('server', '?')}{simulated}{flown}")
    if d["kind"] == "sim":
        link = {"px4": " in PX4 SITL", "mavlink": " as a MAVLink PX4"}.get(d.get("link", ""), "")
        return f"sim {d.get('scenario', '?')}{link}{flown}"
    return f"{d['kind']} {d.get('rigid_body', '?')}@{d.get('server', '?')}{flown}"


def _autopilots(rec, vehicle: str) -> list[str]:
    """The autopilot versions the flight's telemetry named (the recorder's summary, else the telemetry itself)."""
    named = rec.properties.get("summary", {}).get("autopilots")
    if isinstance(named, list) and named:
        return [str(a) for a in named]
    return [a for a in dict.fromkeys(rec.channel("telemetry", vehicle).columns.get("autopilot", [])) if a]


def describe(path: str | Path) -> Entry:
    """One recording's catalog row (an ``error`` row if it cannot be read)."""
    path = Path(path)
    size = path.stat().st_size if path.exists() else 0
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        return Entry(str(path), path.stem, 0, "", "", 0.0, (), (), (), 0, size, "", error=str(exc))
    flight = rec.properties.get("flight", {})
    summary = rec.properties.get("summary", {})
    vehicle = flight.get("vehicle") or (next(iter(rec.vehicles)) if rec.vehicles else "")
    state, est, truth = (rec.channel(c, vehicle) for c in ("state", "estimate", "truth"))
    t = np.asarray(state.columns.get("t_s", []))
    bounds = []
    for ps in rec.channel("params/estimator", vehicle).columns.get("values", []):
        if "lipschitz_bound" in ps:
            bounds.append(float(ps["lipschitz_bound"]))
    params = rec.properties.get("params", {}).get("estimator", {})
    if not bounds and isinstance(params, dict) and "lipschitz_bound" in params:
        bounds.append(float(params["lipschitz_bound"]))
    scenarios = truth.columns.get("scenario", [])
    return Entry(
        path=str(path), flight=flight.get("flight", path.stem), segment=int(flight.get("segment", 0)), vehicle=vehicle,
        scenario=scenarios[0] if len(scenarios) else "", duration_s=float(t[-1] - t[0]) if len(t) > 1 else 0.0,
        pathways=_in_order(est.columns.get("pathway", [])), networks=_in_order(est.columns.get("network_id", [])),
        lipschitz_bounds=_in_order(bounds), samples=len(state), size_bytes=size,
        closed=str(summary.get("end_reason", "")), source=source_of(rec, vehicle))


def recordings_in(directory: str | Path) -> list[Path]:
    """The ``.rrd`` files under ``directory`` (not the recorder's scratch files), oldest first."""
    directory = Path(directory)
    if directory.is_file():
        return [directory]
    return sorted((p for p in directory.rglob("*.rrd") if not p.name.startswith(".")), key=lambda p: (p.stat().st_mtime, p.name))


def catalog(directory: str | Path) -> list[Entry]:
    return [describe(p) for p in recordings_in(directory)]


def format_table(entries: list[Entry]) -> str:
    header = ("flight", "seg", "vehicle", "source", "scenario", "duration", "pathway", "network", "L_N", "size", "ended", "file")
    rows = [header]
    for e in entries:
        if e.error:
            rows.append((e.flight, "-", "-", "-", "-", "-", "-", "-", "-", f"{e.size_bytes / 1e6:.1f} MB", "UNREADABLE", e.path))
            continue
        rows.append((e.flight, str(e.segment), e.vehicle, e.source or "-", e.scenario or "-", f"{e.duration_s:.1f} s",
                     "→".join(e.pathways) or "-", "→".join(e.networks) or "-",
                     "→".join(f"{b:g}" for b in e.lipschitz_bounds) or "-", f"{e.size_bytes / 1e6:.1f} MB",
                     e.closed or "cut short (recorder died)", e.path))
    widths = [max(len(r[i]) for r in rows) for i in range(len(header) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r[:-1], widths)) + "  " + r[-1] for r in rows)
