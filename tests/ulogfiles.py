"""Real ULog bytes made from the PX4 logs in ``tests/data/px4-ulog`` (copied from ``../shared/data``, so a
clone anywhere runs them) for tests and the bench: a topic removed, data
appended after the log closed, a log tiled to any length. Works on the ULog framing itself
(16-byte header, then messages ``uint16 size, uint8 type, payload``; the spec's message types
``B`` flags, ``F`` format, ``A`` add-logged (multi_id u8, msg_id u16, name), ``D`` data (msg_id u16,
fields, the ``timestamp`` field at its format's offset), ``L`` logging (level u8, timestamp u64, text))."""
from __future__ import annotations

import struct
from pathlib import Path

DATA = Path(__file__).resolve().parent / "data" / "px4-ulog"  # pyulog's test logs (BSD-3, LICENSE.md there)
SITL_LOG = DATA / "px4-sitl-takeoff-hover.ulg"
CUBE_LOG = DATA / "cubeorange-flight.ulg"
HEADER = 16
_SIZES = {"int8_t": 1, "uint8_t": 1, "bool": 1, "char": 1, "int16_t": 2, "uint16_t": 2, "int32_t": 4, "uint32_t": 4,
          "float": 4, "int64_t": 8, "uint64_t": 8, "double": 8}


def messages(data: bytes, start: int = HEADER):
    """(offset, type char, payload) of every whole message from ``start`` on."""
    i = start
    while i + 3 <= len(data):
        size, kind = struct.unpack_from("<HB", data, i)
        if i + 3 + size > len(data):
            return
        yield i, chr(kind), data[i + 3:i + 3 + size]
        i += 3 + size


def _formats(data: bytes) -> dict[str, list[tuple[str, int, str]]]:
    out = {}
    for _, kind, payload in messages(data):
        if kind == "F":
            name, fields = payload.decode().split(":", 1)
            parsed = []
            for f in filter(None, fields.split(";")):
                ftype, fname = f.split(" ")
                n = int(ftype[ftype.index("[") + 1:-1]) if "[" in ftype else 0
                parsed.append((ftype.split("[")[0], n, fname))
            out[name] = parsed
    return out


def _size(ftype: str, formats) -> int:
    return _SIZES[ftype] if ftype in _SIZES else sum(_size(t, formats) * max(n, 1) for t, n, _ in formats[ftype])


def timestamp_offsets(data: bytes) -> dict[int, int]:
    """msg_id → byte offset of ``timestamp`` in its data payload (after the msg_id)."""
    formats, out = _formats(data), {}
    for _, kind, payload in messages(data):
        if kind == "A":
            msg_id, name = struct.unpack_from("<H", payload, 1)[0], payload[3:].decode()
            off = 0
            for ftype, n, fname in formats[name]:
                if fname == "timestamp":
                    break
                off += _size(ftype, formats) * max(n, 1)
            out[msg_id] = off
    return out


def topic_ids(data: bytes, topic: str) -> set[int]:
    return {struct.unpack_from("<H", p, 1)[0] for _, k, p in messages(data) if k == "A" and p[3:].decode() == topic}


def without_topics(data: bytes, *topics: str) -> bytes:
    """The log with ``topics`` never subscribed: their ``A`` and ``D`` messages dropped."""
    ids = set().union(*(topic_ids(data, t) for t in topics))
    out = bytearray(data[:HEADER])
    for off, kind, payload in messages(data):
        if kind == "A" and payload[3:].decode() in topics:
            continue
        if kind == "D" and struct.unpack_from("<H", payload)[0] in ids:
            continue
        out += data[off:off + 3 + len(payload)]
    return bytes(out)


def data_messages(data: bytes, topic: str) -> list[bytes]:
    """The whole ``D`` messages (header included) of ``topic``."""
    ids = topic_ids(data, topic)
    return [data[off:off + 3 + len(p)] for off, k, p in messages(data) if k == "D" and struct.unpack_from("<H", p)[0] in ids]


def shifted(message: bytes, offsets: dict[int, int], dt_us: int) -> bytes:
    """A ``D`` message with its timestamp moved by ``dt_us``."""
    m = bytearray(message)
    msg_id = struct.unpack_from("<H", m, 3)[0]
    at = 5 + offsets[msg_id]
    struct.pack_into("<Q", m, at, struct.unpack_from("<Q", m, at)[0] + dt_us)
    return bytes(m)


def resubscribed(data: bytes, topic: str, messages_: list[bytes], msg_id: int, dt_us: int) -> bytes:
    """An ``A`` message subscribing ``topic`` again under ``msg_id``, then ``messages_`` (``D`` messages
    of the topic) under that id, their timestamps moved by ``dt_us``: appended data as a logger
    writes it after the log closed."""
    offsets = timestamp_offsets(data)
    name = topic.encode()
    out = bytearray(struct.pack("<HBBH", 3 + len(name), ord("A"), 0, msg_id) + name)
    for m in messages_:
        moved = bytearray(shifted(m, offsets, dt_us))
        struct.pack_into("<H", moved, 3, msg_id)
        out += moved
    return bytes(out)


def with_appended(data: bytes, extra: bytes) -> bytes:
    """The log with ``extra`` appended after it as ULog appended data (the ``B`` message's
    DATA_APPENDED flag set and its first appended offset at the old end of the file)."""
    off, kind, payload = next(messages(data))
    assert kind == "B", "the flag bits message must come first"
    flags = bytearray(payload)
    flags[8] |= 1  # incompat_flags[0] bit 0: DATA_APPENDED
    struct.pack_into("<Q", flags, 16, len(data))
    return data[:off + 3] + bytes(flags) + data[off + 3 + len(payload):] + extra


def tiled(data: bytes, times: int) -> bytes:
    """The log's data section repeated ``times`` times, each copy's timestamps moved on by the span
    of the log: a longer log at the same rates (definitions and subscriptions once)."""
    offsets = timestamp_offsets(data)
    msgs = list(messages(data))
    first_data = next(i for i, (_, k, _) in enumerate(msgs) if k in "DLO")
    start = struct.unpack_from("<Q", data, 8)[0]  # the header's timestamp: the log's start
    stamps = [struct.unpack_from("<Q", p, 2 + offsets[struct.unpack_from("<H", p)[0]])[0]
              for _, k, p in msgs if k == "D" and struct.unpack_from("<H", p)[0] in offsets]
    span = max(stamps) - start + 10_000
    head = bytearray(data[:msgs[first_data][0]])
    for off, kind, p in msgs[first_data:]:  # every subscription once, before the data
        if kind == "A":
            head += data[off:off + 3 + len(p)]
    body = [(data[off:off + 3 + len(p)], k) for off, k, p in msgs[first_data:] if k != "A"]
    out = head
    for r in range(times):
        for m, kind in body:
            if kind == "D" and struct.unpack_from("<H", m, 3)[0] in offsets:
                out += shifted(m, offsets, r * span)
            elif kind in "LC":  # level u8 (C: then tag u16), timestamp u64
                mm = bytearray(m)
                at = 4 if kind == "L" else 6
                struct.pack_into("<Q", mm, at, struct.unpack_from("<Q", mm, at)[0] + r * span)
                out += mm
            else:
                out += m
    return bytes(out)
