"""Where PX4 SITL is and how it is started with the world's airframe (pure: paths, parameters, a command
line; ``neso px4`` runs it). ``sim/px4/build.sh`` (``make px4``, part of ``make setup``) builds it into
:func:`px4_home`; ``sim/px4/neso_quad.params`` is the world's airframe, each value with its source."""
from __future__ import annotations

import os
from pathlib import Path

PX4_VERSION = "v1.16.0"
PARAMS_FILE = Path(__file__).resolve().parent / "px4" / "neso_quad.params"
SIM_MODEL = "none_iris"  # airframe 10016: a quad X driven by an external simulator over simulator_mavlink
SIM_TCP_PORT = 4560  # + instance: PX4 connects to the simulator there (px4-rc.mavlinksim)
OFFBOARD_UDP_PORT = 14540  # + instance: PX4's offboard/API MAVLink link sends there (px4-rc.mavlink)


def px4_home() -> Path:
    """The built SITL (``bin/px4``, ``etc/``): ``$NESO_PX4_HOME``, default ~/.cache/neso/px4-v1.16.0."""
    return Path(os.environ.get("NESO_PX4_HOME") or Path.home() / ".cache" / "neso" / f"px4-{PX4_VERSION}")


def px4_binary() -> Path:
    return px4_home() / "bin" / "px4"


def missing_px4() -> str:
    """Why PX4 SITL cannot start (one line), or "" when it is built."""
    binary = px4_binary()
    if binary.is_file() and os.access(binary, os.X_OK):
        return ""
    return (f"PX4 SITL is not built ({binary} missing): run `make setup` (it builds PX4 {PX4_VERSION} from $PX4_SRC, "
            "../shared/px4/ or PX4's repository: sim/px4/build.sh)")


def load_params(path: Path | str = PARAMS_FILE) -> dict[str, str]:
    """``NAME VALUE`` lines (``#`` comments) → {NAME: VALUE}; a malformed line raises ValueError naming it."""
    params: dict[str, str] = {}
    for number, line in enumerate(Path(path).read_text().splitlines(), 1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) != 2 or not fields[0].replace("_", "").isalnum() or not fields[0].isupper():
            raise ValueError(f"{path}:{number}: expected 'NAME VALUE', got {line.strip()!r}")
        try:
            float(fields[1])
        except ValueError:
            raise ValueError(f"{path}:{number}: {fields[0]}'s value {fields[1]!r} is not a number") from None
        params[fields[0]] = fields[1]
    return params


def sitl_command(instance: int = 0, params: dict[str, str] | None = None,
                 base_env: dict[str, str] | None = None) -> tuple[list[str], dict[str, str]]:
    """(argv, environment) that start PX4 SITL instance ``instance`` (simulator TCP port 4560 + instance,
    offboard link to UDP 14540 + instance) as a daemon with the world's airframe parameters, to be run
    in an empty working folder of its own (PX4 keeps its parameters, dataman and logs there)."""
    env = dict(os.environ if base_env is None else base_env)
    env["PX4_SIM_MODEL"] = SIM_MODEL
    for name, value in (load_params() if params is None else params).items():
        env[f"PX4_PARAM_{name}"] = value
    home = px4_home()
    return [str(home / "bin" / "px4"), "-d", "-i", str(instance), str(home / "etc")], env
