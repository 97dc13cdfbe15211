"""Where the selected vehicle's samples come from, in one line: live, or a replay and of what.

Kept apart from the title line so it can move with it: :func:`provenance_line` reads only the
vehicle model. A replay (``neso replay --to-bus``) announces itself on ``neso/<v>/replay``
(:class:`runtime.schema.ReplayMsg`: the file, what it records, progress); its states also carry
``source="replay"``, which is enough to say "not live" when no announcement came.
"""
from __future__ import annotations

from dashboard.model import VehicleModel

REPLAY_FRESH_S = 3.0  # an announcement younger than this means the replay is running


def provenance_line(v: VehicleModel, now_s: float) -> str:
    """Markdown: ``LIVE`` with the state source, or ``REPLAY (not live)`` with its origin and file."""
    replay, state = v.latest.get("replay"), v.latest.get("state")
    state_fresh = state is not None and now_s - v.received.get("state", -1e9) < REPLAY_FRESH_S
    if state_fresh and state.source != "replay":
        return f"● **LIVE** · state from {state.source}"
    if replay is not None and replay.playing and now_s - v.received.get("replay", -1e9) < REPLAY_FRESH_S:
        return (f"▶ **REPLAY (not live)** · {replay.origin} · `{replay.file}` · "
                f"{replay.t_s:.1f} / {replay.duration_s:.1f} s at ×{replay.speed:g}")
    if replay is not None and (not replay.playing or not state_fresh):
        return f"■ replay ended · {replay.origin} · `{replay.file}` ({replay.duration_s:.1f} s)"
    if state_fresh:
        return "▶ **REPLAY (not live)** · origin not announced"
    return "no samples"
