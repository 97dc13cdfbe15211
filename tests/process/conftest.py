"""Fixtures shared by process tests."""
from __future__ import annotations

import os
import subprocess

import pytest


@pytest.fixture(scope="module")
def rerun_home(tmp_path_factory):
    """The `rerun` CLI writes analytics settings under the config folder on its first run: give it
    (and the processes started from here, which inherit it) a temporary one, analytics off."""
    from recordings.reader import rerun_cli

    home = tmp_path_factory.mktemp("rerun-config")
    old = os.environ.get("XDG_CONFIG_HOME")
    os.environ["XDG_CONFIG_HOME"] = str(home)
    subprocess.run([rerun_cli(), "analytics", "disable"], capture_output=True, timeout=60, check=True)
    yield home
    if old is None:
        os.environ.pop("XDG_CONFIG_HOME", None)
    else:
        os.environ["XDG_CONFIG_HOME"] = old
