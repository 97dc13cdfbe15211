"""Live parameters: declared with type and range, set all-or-nothing, applied at a tick boundary.

A service declares its parameters as :class:`Param` specs and may add a ``check`` that
sees the whole proposed set (for rules that depend on the service's state, such as "no
Lipschitz bound above the one the network was trained to"). :meth:`ParamSet.request`
validates a set request and either refuses it with the reason (nothing changes) or stores
it as pending; the service takes the pending values with :meth:`ParamSet.take_pending` at
its next tick boundary, so a change never lands in the middle of a step.

A check may refuse in a way the operator can override (:class:`Refusal` with ``overridable``:
the stability certificate): a request carrying ``override: true`` is then accepted, and the
refusal it overrode is kept for the service to report (:meth:`ParamSet.take_overrides`), so the
flight's record says who flew outside the certificate and by how much. A ``prepare`` hook runs
before the check, outside any lock of the service, for slow work the check then finds cached.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, Callable


OVERRIDE = "override"  # the request key that overrides an overridable refusal


@dataclass(frozen=True)
class Refusal:
    """Why a check refuses; ``overridable``: ``override: true`` in the request accepts it anyway."""

    reason: str
    overridable: bool = False


Check = Callable[[dict[str, Any]], "str | Refusal | None"]


@dataclass(frozen=True)
class Param:
    """One live parameter. ``kind`` is ``float``, ``int``, ``bool`` or ``str``; ``choices``
    restricts a ``str``; ``lo``/``hi`` bound a number (inclusive)."""

    name: str
    default: Any
    kind: type
    doc: str
    unit: str = ""
    choices: tuple[str, ...] | None = None
    lo: float = -math.inf
    hi: float = math.inf

    def coerce(self, value: Any) -> Any:
        """``value`` as this parameter's type, or ``ValueError`` saying why it is not valid."""
        if self.kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{self.name} must be true or false, got {value!r}")
            return value
        if self.kind is str:
            if not isinstance(value, str):
                raise ValueError(f"{self.name} must be a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise ValueError(f"{self.name} must be one of {list(self.choices)}, got {value!r}")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{self.name} must be a number, got {value!r}")
        if self.kind is int and value != int(value):
            raise ValueError(f"{self.name} must be an integer, got {value!r}")
        value = self.kind(value)
        if not (math.isfinite(value) and self.lo <= value <= self.hi):
            raise ValueError(f"{self.name} = {value!r} is outside [{self.lo:g}, {self.hi:g}] {self.unit}".rstrip())
        return value


class ParamSet:
    """Current values, pending changes and validation for one service's parameters."""

    def __init__(self, specs: tuple[Param, ...], initial: dict[str, Any] | None = None,
                 check: Check | None = None, prepare: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.specs = {p.name: p for p in specs}
        self._check = check
        self._prepare = prepare
        self._overrides: list[str] = []
        self._lock = threading.Lock()
        values = {p.name: p.default for p in specs}
        for name, value in (initial or {}).items():
            values[name] = self._spec(name).coerce(value)
        self._values = values
        self._pending: dict[str, Any] = {}

    def _spec(self, name: str) -> Param:
        try:
            return self.specs[name]
        except KeyError:
            raise ValueError(f"unknown parameter {name!r}; known: {sorted(self.specs)}") from None

    def values(self) -> dict[str, Any]:
        """The values in effect, with any accepted but not yet applied change on top."""
        with self._lock:
            return {**self._values, **self._pending}

    def effective(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._values)

    def prepare(self, changes: dict[str, Any]) -> None:
        """Run the ``prepare`` hook on the values ``changes`` would give (nothing if they are invalid)."""
        if self._prepare is None or not isinstance(changes, dict):
            return
        try:
            coerced = {n: self._spec(n).coerce(v) for n, v in changes.items() if n != OVERRIDE}
        except ValueError:
            return
        self._prepare({**self.values(), **coerced})

    def request(self, changes: dict[str, Any]) -> tuple[bool, str, dict[str, Any]]:
        """Validate ``changes``; (accepted, reason if refused, values that will be in effect).
        ``changes`` may carry ``override: true`` (module docstring)."""
        if not isinstance(changes, dict) or not changes:
            return False, "a set request needs at least one name: value", self.values()
        changes = dict(changes)
        override = changes.pop(OVERRIDE, False)
        if not isinstance(override, bool):
            return False, f"{OVERRIDE} must be true or false, got {override!r}", self.values()
        if not changes:
            return False, "a set request needs at least one name: value besides override", self.values()
        try:
            coerced = {name: self._spec(name).coerce(value) for name, value in changes.items()}
        except ValueError as exc:
            return False, str(exc), self.values()
        with self._lock:
            proposed = {**self._values, **self._pending, **coerced}
            verdict = self._check(proposed) if self._check is not None else None
            if isinstance(verdict, str):
                verdict = Refusal(verdict) if verdict else None
            if verdict is not None:
                if not (override and verdict.overridable):
                    hint = " (send override=true to apply it anyway)" if verdict.overridable else ""
                    return False, verdict.reason + hint, {**self._values, **self._pending}
                self._overrides.append(f"{coerced} applied by override: {verdict.reason}")
            self._pending.update(coerced)
            return True, "", proposed

    def take_overrides(self) -> list[str]:
        """The refusals overridden since the last call (to report as events)."""
        with self._lock:
            out, self._overrides = self._overrides, []
            return out

    def take_pending(self) -> dict[str, Any]:
        """The changes accepted since the last call (empty if none), now in effect."""
        with self._lock:
            if not self._pending:
                return {}
            changed = {k: v for k, v in self._pending.items() if self._values[k] != v}
            self._values.update(self._pending)
            self._pending = {}
            return changed
