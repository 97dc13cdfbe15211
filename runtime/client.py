"""Asking services things from outside: parameter get/set and commands, as one-shot queries."""
from __future__ import annotations

import time
import uuid

from runtime.schema import OFFER_COMMANDS, CommandReply, CommandRequest, Keys, ParamReply, ParamRequest, SchemaError


class ServiceUnavailable(RuntimeError):
    """No reply from the service (not running, or not reachable on this bus)."""


def _query(session, key: str, payload: bytes, reply_type, timeout_s: float):
    """The first reply to a query on ``key`` within ``timeout_s``. Each attempt waits for the answer until the
    deadline: a service that takes seconds to check a change (certifying a network on a busy machine) answers within
    it. (Attempts of 0.25 s each missed every answer slower than that, and each one re-asked queued the same check
    again behind the first: the dashboard showed "no reply" for an L_N the estimator applied.) A query no service
    took (a session that has just opened may not know the service's queryable yet) ends at once and is asked again
    (a get or a set of absolute values is idempotent; a command carries a request id the service answers once,
    :class:`runtime.node.AnsweredOnce`)."""
    deadline = time.monotonic() + timeout_s
    while True:
        for reply in session.get(key, payload=payload, timeout=max(0.05, deadline - time.monotonic())):
            if reply.ok is None:  # the service's refusal (a reply_type), or Zenoh's own "Timeout": ask again
                try:
                    return reply_type.from_bytes(reply.err.payload.to_bytes())
                except SchemaError:
                    continue
            try:
                return reply_type.from_bytes(reply.ok.payload.to_bytes())
            except SchemaError as exc:
                raise ServiceUnavailable(f"{key}: unreadable reply ({exc})") from None
        if time.monotonic() >= deadline:
            raise ServiceUnavailable(f"no reply on {key} within {timeout_s:g} s: is the service running?")
        time.sleep(0.02)


def get_params(session, keys: Keys, service: str, timeout_s: float = 2.0) -> ParamReply:
    return _query(session, keys.param(service), ParamRequest(op="get").to_bytes(), ParamReply, timeout_s)


def read_params(session, keys: Keys, service: str, timeout_s: float = 2.0) -> ParamReply:
    """The parameters, asked on the read-only key every identity of a secure bus may query."""
    return _query(session, keys.params(service), ParamRequest(op="get").to_bytes(), ParamReply, timeout_s)


def set_params(session, keys: Keys, service: str, values: dict, timeout_s: float = 2.0) -> ParamReply:
    return _query(session, keys.param(service), ParamRequest(op="set", values=values).to_bytes(), ParamReply, timeout_s)


def command(session, keys: Keys, service: str, name: str, args: dict | None = None,
            timeout_s: float = 2.0) -> CommandReply:
    """Ask ``service`` to do ``name``. The request carries a fresh ``request`` id (unless ``args``
    has one), so the service does it once however often the query is repeated. An ``offer`` goes
    to the service's ``offer`` key (on a secure bus only the trainer may send it)."""
    args = {"request": uuid.uuid4().hex, **(args or {})}
    key = keys.offer(service) if name in OFFER_COMMANDS else keys.cmd(service)
    return _query(session, key, CommandRequest(name=name, args=args).to_bytes(), CommandReply, timeout_s)
