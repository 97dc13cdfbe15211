"""The role certificate's verified frontier per gains, kept between processes: a started or restarted estimator
adopts the one found before — after verifying it in numpy exactly as the solver's own results are
(:func:`neso.certificate.roles.adopt_frontier`) — instead of importing cvxpy and solving SDPs again (measured:
~1.5 s of its start, most of it cvxpy's import). A missing, stale, unreadable or tampered entry is only ever
a slower start: it is solved again and written back. One JSON file, ``$XDG_CACHE_HOME/neso/role-certificates.json``
(default ``~/.cache``), replaced atomically."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from neso.certificate.roles import adopt_frontier, frontier_certificate

VERSION = 1


def cache_path() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "neso" / "role-certificates.json"


def _key(kp: float, kd: float, omega_o: float) -> str:
    return f"{float(kp)!r},{float(kd)!r},{float(omega_o)!r}"


def _read(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data.get("frontiers", {}) if isinstance(data, dict) and data.get("version") == VERSION else {}


def warm(kp: float, kd: float, omega_o: float, path: Path | None = None) -> str:
    """Make the gains' frontier known to this process: adopted from the cache if it verifies, else solved and
    written to it. Returns what happened ("adopted", "solved", or "solved, not cached: <why>")."""
    path = path or cache_path()
    entry = _read(path).get(_key(kp, kd, omega_o))
    if isinstance(entry, dict) and adopt_frontier(kp, kd, omega_o, entry.get("lmax"), entry.get("p"), entry.get("tau")):
        return "adopted"
    lmax, p, tau = frontier_certificate(kp, kd, omega_o)
    if p is None:
        return "solved"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        frontiers = _read(path)
        frontiers[_key(kp, kd, omega_o)] = {"lmax": lmax, "p": p.tolist(), "tau": tau}
        with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=".role-certificates-", delete=False) as f:
            json.dump({"version": VERSION, "frontiers": frontiers}, f)
        os.replace(f.name, path)
    except OSError as exc:
        return f"solved, not cached: {exc}"
    return "solved"
