"""Command-line options generated from a service's config dataclass, so every default lives there once.

A config field becomes an option when it is declared with :func:`option`: the flag is ``--`` and the
field name with dashes (or ``flag``), the default and its unit are the field's and appear in
``--help``. ``cli=(to_cli, from_cli)`` converts when the command line speaks another unit or form
than the field (a period in s typed as a rate in Hz, a tuple typed as a comma-separated list). A
boolean whose default is ``False`` is a switch; one whose default is ``True`` needs a ``flag`` that
turns it off (``--no-learn-hover``, ``--manual``). A field holding a nested config declared with ``option(nested=True)``
contributes that config's options.

    parser = argparse.ArgumentParser(); add_options(parser, EstimatorConfig)
    config = config_from_options(EstimatorConfig, parser.parse_args(), lockstep=True)
"""
from __future__ import annotations

import argparse
import dataclasses
from typing import Any, Callable

_KEY = "option"


@dataclasses.dataclass(frozen=True)
class Option:
    help: str
    unit: str = ""
    flag: str | None = None
    choices: tuple | None = None
    cli: tuple[Callable[[Any], Any], Callable[[Any], Any]] | None = None
    nested: bool = False


def option(default: Any = dataclasses.MISSING, *, help: str = "", unit: str = "", flag: str | None = None,
           choices: tuple | None = None, cli: tuple[Callable, Callable] | None = None, nested: bool = False,
           default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field that is also a command-line option (see the module's docstring)."""
    return dataclasses.field(default=default, default_factory=default_factory,
                             metadata={_KEY: Option(help, unit, flag, tuple(choices) if choices else None, cli, nested)})


def comma_list() -> tuple[Callable, Callable]:
    """``cli=`` for a tuple of names typed as ``a,b,c`` (``''``: none)."""
    return (lambda names: ",".join(names), lambda text: tuple(s for s in text.split(",") if s))


def rate_of_period() -> tuple[Callable, Callable]:
    """``cli=`` for a period field (s) typed as a rate (Hz)."""
    return (lambda period_s: 1.0 / period_s, lambda rate_hz: 1.0 / rate_hz)


def _fields(cls) -> list[tuple[dataclasses.Field, Option]]:
    return [(f, f.metadata[_KEY]) for f in dataclasses.fields(cls) if _KEY in f.metadata]


def _default(f: dataclasses.Field) -> Any:
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def _dest(prefix: str, name: str) -> str:
    return f"cfg__{prefix}{name}"


def add_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls, *, _prefix: str = "",
                _defaults: Any = None) -> None:
    """Add an option to ``parser`` for every :func:`option` field of the config class ``cls`` (in a
    group named after it)."""
    if isinstance(parser, argparse.ArgumentParser):
        parser = parser.add_argument_group(f"options of {cls.__name__} ({cls.__module__})")
    for f, opt in _fields(cls):
        default = getattr(_defaults, f.name) if _defaults is not None else _default(f)
        if opt.nested:
            add_options(parser, type(default), _prefix=f"{_prefix}{f.name}__", _defaults=default)
            continue
        flag = opt.flag or "--" + f.name.replace("_", "-")
        shown = opt.cli[0](default) if opt.cli else default
        unit = f" [{opt.unit}]" if opt.unit else ""
        dest = _dest(_prefix, f.name)
        if isinstance(default, bool) and opt.cli is None:
            if default and opt.flag is None:
                raise ValueError(f"{cls.__name__}.{f.name}: a switch that defaults to on needs a flag that turns it off")
            parser.add_argument(flag, dest=dest, action="store_false" if default else "store_true", help=opt.help)
            continue
        kind = type(shown) if isinstance(shown, (int, float, str)) else str
        help_text = f"{opt.help}{unit}; default %(default)s" if opt.help else f"default %(default)s{unit}"
        parser.add_argument(flag, dest=dest, type=kind, default=shown, choices=opt.choices, help=help_text,
                            metavar=None if opt.choices else flag.lstrip("-").replace("-", "_").upper())


def config_from_options(cls, args: argparse.Namespace, **fixed: Any):
    """``cls`` built from the options :func:`add_options` added (fields without one keep their
    defaults; ``fixed`` sets fields the command line does not, e.g. ``lockstep``). A value the
    config refuses ends the program with its reason in one line (``SystemExit``), no traceback."""
    try:
        return _build(cls, args, "", None, fixed)
    except ValueError as exc:
        raise SystemExit(f"{cls.__name__}: {exc}") from None


def _build(cls, args: argparse.Namespace, _prefix: str, _defaults: Any, fixed: dict[str, Any]):
    values: dict[str, Any] = {}
    for f, opt in _fields(cls):
        default = getattr(_defaults, f.name) if _defaults is not None else _default(f)
        if opt.nested:
            values[f.name] = _build(type(default), args, f"{_prefix}{f.name}__", default, {})
            continue
        value = getattr(args, _dest(_prefix, f.name))
        values[f.name] = opt.cli[1](value) if opt.cli else value
    values.update(fixed)
    return dataclasses.replace(_defaults, **values) if _defaults is not None else cls(**values)
