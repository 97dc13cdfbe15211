"""Role certificates kept between processes: a started or restarted estimator adopts the certificates found before
for its network and gains — after verifying every one in numpy exactly as the solver's own results are
(:func:`neso.certificate.roles.adopt_certificate`) — instead of importing cvxpy and solving SDPs again (measured:
~1.5 s of its start, most of it cvxpy's import). A missing, stale, unreadable or tampered entry is only ever a slower
start: it is solved again and written back. One JSON file, ``$XDG_CACHE_HOME/neso/role-certificates.json`` (default
``~/.cache``), replaced atomically.

Flight budgets the same way (:func:`adopt_budgets`, :func:`keep_budgets`; ``flight-budgets.json`` beside it): the
largest slope a recipe may spend at given gains, which the trainer and ``neso experiment paper`` bisect over ~17 role
certificates (~10 s at the paper's gains), is verified with one (~0.6 s) when a process on this machine found it
before. A wrong entry is at worst a smaller budget than the largest (still certified), never an uncertified one."""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict
from pathlib import Path

from neso.certificate import POLICY, CertificatePolicy, LoopPlant, NetworkSlopes, ReferenceBounds
from neso.certificate.flight import role_inputs
from neso.certificate.roles import RoleInputs, adopt_certificate, certificate_data, certify_roles

VERSION = 2


def cache_path() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "neso" / "role-certificates.json"


def _key(inputs: RoleInputs) -> str:
    return json.dumps({k: float(v) for k, v in asdict(inputs).items()}, sort_keys=True)


def _read(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data.get("certificates", {}) if isinstance(data, dict) and data.get("version") == VERSION else {}


def warm(questions: list[RoleInputs], path: Path | None = None) -> str:
    """Make the role certificates for ``questions`` known to this process: adopted from the cache where they verify,
    else solved and written to it. Returns what happened ("adopted", "solved", or "solved, not cached: <why>")."""
    path = path or cache_path()
    known = _read(path)
    solved = {}
    for inputs in questions:
        entry = known.get(_key(inputs))
        if isinstance(entry, dict) and adopt_certificate(inputs, entry):
            continue
        data = certificate_data(inputs, certify_roles(inputs))
        if data is not None:
            solved[_key(inputs)] = data
    if not solved:
        return "adopted"
    try:
        _replace(path, {"version": VERSION, "certificates": {**_read(path), **solved}})
    except OSError as exc:
        return f"solved, not cached: {exc}"
    return "solved"


def _replace(path: Path, data: dict) -> None:
    """``data`` as the JSON file at ``path``, replaced atomically (its folder made if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.stem}-", delete=False) as f:
        json.dump(data, f)
    os.replace(f.name, path)


def warm_flight(slopes: NetworkSlopes, kp: float, kd: float, omega_o: float, plant: LoopPlant,
                policy: CertificatePolicy = POLICY, path: Path | None = None) -> str:
    """:func:`warm` for what :func:`neso.certificate.flight_certificate` asks of a network with ``slopes`` and of
    PD+ESO (no network) at these gains on ``plant``."""
    envelope = ReferenceBounds.envelope(policy)
    return warm([role_inputs(slopes, kp, kd, omega_o, plant, envelope, policy),
                 role_inputs(NetworkSlopes(0.0), kp, kd, omega_o, plant, envelope, policy)], path)


# ------------------------------------------------------------------------------------------------ flight budgets
def budgets_version() -> str:
    """The certificate's code as it is here (a digest of ``neso/certificate/*.py``): a budget found by other code is
    not read, so an edit to the mathematics never meets a budget that only held before it."""
    import hashlib

    import neso.certificate

    digest = hashlib.sha256()
    for source in sorted(Path(neso.certificate.__file__).parent.glob("*.py")):
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    return digest.hexdigest()[:16]


def budgets_path() -> Path:
    """Beside the role certificates: ``$XDG_CACHE_HOME/neso/flight-budgets.json``."""
    return cache_path().with_name("flight-budgets.json")


def _read_budgets(path: Path) -> dict:
    """The budgets in the file at ``path`` written by this certificate code; none if missing, unreadable or other."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    budgets = data.get("budgets") if isinstance(data, dict) and data.get("version") == budgets_version() else None
    return budgets if isinstance(budgets, dict) else {}


def adopt_budgets(path: Path | None = None) -> int:
    """Make the flight budgets found before (by any process on this machine) known to this one, each to be verified
    before use (:func:`neso.certificate.flight.adopt_budget`); how many. A missing or unreadable file is none."""
    from neso.certificate.flight import adopt_budget

    budgets = _read_budgets(path or budgets_path())
    return sum(adopt_budget(key, value) for key, value in budgets.items() if isinstance(key, str))


def keep_budgets(path: Path | None = None) -> str:
    """Write the budgets this process found (:data:`neso.certificate.flight.FOUND_BUDGETS`) into the file, merged
    with what is there, replaced atomically: "kept N", "nothing new", or "not kept: <why>"."""
    from neso.certificate.flight import FOUND_BUDGETS

    path = path or budgets_path()
    known = _read_budgets(path)
    new = {k: v for k, v in FOUND_BUDGETS.items() if known.get(k) != v}
    if not new:
        return "nothing new"
    try:
        _replace(path, {"version": budgets_version(), "budgets": {**known, **new}})
    except OSError as exc:
        return f"not kept: {exc}"
    return f"kept {len(new)}"
