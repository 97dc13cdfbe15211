"""What a secure hub refused, read from Zenoh's own log, counted and told in one line each.

Zenoh (1.10, this wheel built without its ``stats`` feature) counts nothing it drops; it only
logs. With ``warn,zenoh::net::routing::interceptor=trace`` the router logs every ACL decision
("<zid> on …CertCommonName(<cn>)… is unauthorized to Query (ingress) on <key>", or later
"Using cached result: <zid> is unauthorized to …") and, right after a dropped message,
"Msg intercepted!" on the same thread; and a TLS handshake it refuses as a WARN
("invalid peer certificate: UnknownIssuer", "… certificate expired …").
:class:`RefusalCounter` turns those lines into counts per (identity, message, key) and per TLS
reason. :func:`capture_zenoh_log` routes the log (Zenoh writes it to file descriptor 1) into it.
"""
from __future__ import annotations

import os
import re
import sys
import threading
from collections import Counter
from typing import Callable

LOG_FILTER = "warn,zenoh::net::routing::interceptor=trace"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"\s(\S+ ThreadId\(\d+\))\s")
_DECISION = re.compile(r"(?:Using cached result: )?([0-9a-f]+)(?: on (\S+))? is unauthorized to (.+?) on (\S+)\s*$")
_CN = re.compile(r"CertCommonName\(([^)]*)\)")
_TLS = re.compile(r"invalid peer certificate: (.+?)(?:\. Hint:.*)?$")


class RefusalCounter:
    """Feed it Zenoh log lines; it counts refusals and says what to report (``feed`` → text or None)."""

    def __init__(self) -> None:
        self.messages: Counter[tuple[str, str, str]] = Counter()  # (identity, message, key) → dropped
        self.links: Counter[str] = Counter()  # TLS refusal reason → links refused
        self._names: dict[str, str] = {}  # zid → certificate common name
        self._pending: dict[str, tuple[str, str, str]] = {}  # thread → its last "unauthorized" decision

    def feed(self, line: str) -> str | None:
        line = _ANSI.sub("", line).rstrip()
        thread = _THREAD.search(line)
        thread_id = thread.group(1) if thread else ""
        if " is authorized to " in line:
            self._pending.pop(thread_id, None)
            return None
        decision = _DECISION.search(line)
        if decision:
            zid, subject, what, key = decision.groups()
            cn = _CN.search(subject or "")
            if cn:
                self._names[zid] = cn.group(1)
            self._pending[thread_id] = (self._names.get(zid, f"zid {zid}"), what, key)
            return None
        if line.endswith("Msg intercepted!") and thread_id in self._pending:
            refused = self._pending.pop(thread_id)
            self.messages[refused] += 1
            n = self.messages[refused]
            if _is_power_of_ten(n):
                who, what, key = refused
                return f"access control refused {what} on {key} from {who} ({n} so far)"
            return None
        tls = _TLS.search(line)
        if tls:
            reason = re.sub(r"verification time \d+.*", "", tls.group(1)).rstrip(": ")
            self.links[reason] += 1
            n = self.links[reason]
            return f"refused a TLS link: {reason} ({n} so far)" if _is_power_of_ten(n) else None
        return None


def _is_power_of_ten(n: int) -> bool:
    while n % 10 == 0 and n > 1:
        n //= 10
    return n == 1


def capture_zenoh_log(on_line: Callable[[str], None], level: str = LOG_FILTER) -> None:
    """Start Zenoh's log at ``level`` (``RUST_LOG`` overrides) with every line handed to
    ``on_line`` on a reader thread. Zenoh writes to fd 1: that becomes a pipe, and Python's
    ``sys.stdout`` moves to a copy of the real stdout. Call once, before opening a session."""
    import zenoh

    sys.stdout.flush()
    real_stdout = os.dup(1)
    sys.stdout = os.fdopen(real_stdout, "w", buffering=1)
    read_end, write_end = os.pipe()
    os.dup2(write_end, 1)
    os.close(write_end)

    def pump() -> None:
        with os.fdopen(read_end, errors="replace") as lines:
            for line in lines:
                on_line(line)
    threading.Thread(target=pump, name="zenoh-log", daemon=True).start()
    zenoh.init_log_from_env_or(level)
