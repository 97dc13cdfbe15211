"""The layers of docs/architecture.md "Layout": no import runs up, and the step objects never read a clock.

Every import counts, also one inside a function (a lazy import is still an arrow)."""
from __future__ import annotations

import ast
from pathlib import Path

from tests.helpers import REPO

# folder → the project's folders it may import (docs/architecture.md "Layout"); cli and bench sit on top of all
# of them
MAY_IMPORT = {
    "neso": set(),
    "sim": {"neso"},
    "runtime": {"neso"},
    "flight": {"neso", "sim", "runtime"},
    "recordings": {"neso", "sim", "runtime", "flight"},
    "services": {"neso", "sim", "runtime", "flight", "recordings"},
    "dashboard": {"neso", "sim", "runtime", "flight", "recordings"},
}
PACKAGES = set(MAY_IMPORT) | {"cli", "bench"}


def imported_modules(path: Path) -> list[str]:
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
        elif isinstance(node, ast.Import):
            names += [a.name for a in node.names]
    return names


def test_no_import_runs_up_the_layers():
    arrows_up = []
    for folder, allowed in MAY_IMPORT.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            for module in imported_modules(path):
                top = module.split(".")[0]
                if top in PACKAGES and top != folder and top not in allowed:
                    arrows_up.append(f"{path.relative_to(REPO)} imports {module}")
    assert arrows_up == [], "move the shared part down a layer (docs/architecture.md 'Layout')"


def test_the_step_objects_are_clock_free():
    """Time comes in as an argument (``now_s``, ``t_s``) or as the ``clock`` their adapter hands them."""
    readers = [f"{p.relative_to(REPO)} imports {m}" for p in sorted((REPO / "flight").rglob("*.py"))
               for m in imported_modules(p) if m.split(".")[0] in ("time", "datetime")]
    assert readers == []


def test_every_layer_is_packaged_and_in_the_image():
    pyproject = (REPO / "pyproject.toml").read_text()
    dockerfile = (REPO / "Dockerfile").read_text().splitlines()
    for folder in sorted(PACKAGES - {"bench"}):
        assert f'"{folder}*"' in pyproject, f"{folder} missing from [tool.setuptools.packages.find]"
        assert f"COPY {folder} {folder}" in dockerfile, f"{folder} missing from the Dockerfile"
