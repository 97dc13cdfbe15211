"""The PX4 tier: real PX4 v1.16.0 SITL in the loop."""
from __future__ import annotations

from pathlib import Path

from services.certificate_cache import cache_path
from sim.px4_sitl import px4_home


def px4_env(home) -> dict[str, str]:
    """The environment changes a PX4 test's `neso` runs with: MAVSDK writes its cache under $HOME/.cache/mavsdk, so a
    HOME of the test's own (``home``); PX4 stays where make setup put it. The certificates and flight budgets this
    machine found before stay known: ``home``/.cache/neso is made a link to where every other test's processes keep
    them (each verified before use, services/certificate_cache.py). Without it they were solved again under the test's
    HOME: test_px4_paper.py's budgets, 12 s of its built-in world's 27 on a quiet machine."""
    caches = cache_path().parent
    caches.mkdir(parents=True, exist_ok=True)
    link = Path(home) / ".cache" / "neso"
    link.parent.mkdir(parents=True, exist_ok=True)
    if not link.is_symlink():
        link.symlink_to(caches, target_is_directory=True)
    return {"HOME": str(home), "NESO_PX4_HOME": str(px4_home())}
