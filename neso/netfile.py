"""Network files: safetensors layout written with numpy + json + struct (never pickle).

Layout (https://github.com/huggingface/safetensors): 8-byte little-endian u64 ``H``; ``H`` bytes of
UTF-8 JSON header (space-padded so the data starts 8-byte aligned); then the raw little-endian
tensor bytes. Header: ``{name: {"dtype": "F64", "shape": [...], "data_offsets": [begin, end]},
"__metadata__": {str: str}}`` with offsets relative to the start of the data section.

Tensors: ``layers.{i}.weight`` (n_out_i, n_in_i), ``layers.{i}.bias`` (n_out_i,), ``input_mean``,
``input_std`` (n_in,), ``output_mean``, ``output_std`` (n_out,), physical units.

Metadata owned by the format (computed on save, overriding any same-named key of the network's
own metadata, and stripped from ``LipschitzMLP.metadata`` on load): ``format``,
``format_version``, ``n_layers``, ``lipschitz_bound`` with ``lipschitz_bound_units``
(``normalised`` or ``physical``), ``lipschitz_bound_physical``, ``certified_lipschitz_normalised``,
``certified_lipschitz_physical``. Version 1 files stated ``lipschitz_bound_normalised`` only and
still load. Every other key is the network's own metadata (id, ``feature_set``, thrust lag,
validation loss, training data reference, certificate, ...) and round-trips.

Loading is a gate: anything malformed, non-finite, inconsistent, a feature set this version
cannot build (or whose size is not the network's), or an exact SVD certificate above its stated
bound raises ``NetworkFileError`` naming the reason.
"""
from __future__ import annotations

import json
import math
import os
import struct
import tempfile

import numpy as np

from neso.features import FeatureSetError
from neso.network import BOUND_UNITS, LipschitzMLP

FORMAT = "neso-lipschitz-mlp"
FORMAT_VERSION = "2"
READABLE_VERSIONS = ("1", "2")
CERT_RTOL = 1e-6
MAX_HEADER_BYTES = 100_000_000  # safetensors' own cap
RESERVED_KEYS = frozenset({
    "format", "format_version", "n_layers", "lipschitz_bound", "lipschitz_bound_units",
    "lipschitz_bound_normalised", "lipschitz_bound_physical",
    "certified_lipschitz_normalised", "certified_lipschitz_physical",
})
_DTYPES = {"F64": np.dtype("<f8"), "F32": np.dtype("<f4")}


class NetworkFileError(ValueError):
    """A network file was refused; the message says why."""


def _tensors(net: LipschitzMLP) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for i, (w, b) in enumerate(zip(net.weights, net.biases)):
        out[f"layers.{i}.weight"] = w
        out[f"layers.{i}.bias"] = b
    out["input_mean"] = net.input_mean
    out["input_std"] = net.input_std
    out["output_mean"] = net.output_mean
    out["output_std"] = net.output_std
    return out


def network_to_bytes(net: LipschitzMLP) -> bytes:
    """Serialise ``net`` (float64 tensors) with its certificate and bounds in the metadata."""
    meta = {str(k): str(v) for k, v in net.metadata.items()}
    meta.update({
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "n_layers": str(net.n_layers),
        "lipschitz_bound": repr(float(net.lipschitz_bound)),
        "lipschitz_bound_units": net.bound_units,
        "lipschitz_bound_physical": repr(net.lipschitz_bound_physical()),
        "certified_lipschitz_normalised": repr(net.certified_lipschitz_normalised()),
        "certified_lipschitz_physical": repr(net.certified_lipschitz_physical()),
    })
    header: dict[str, object] = {}
    chunks: list[bytes] = []
    offset = 0
    for name, arr in _tensors(net).items():
        raw = np.ascontiguousarray(arr, dtype="<f8").tobytes()
        header[name] = {"dtype": "F64", "shape": list(arr.shape), "data_offsets": [offset, offset + len(raw)]}
        chunks.append(raw)
        offset += len(raw)
    header["__metadata__"] = meta
    hbytes = json.dumps(header, separators=(",", ":"), sort_keys=False).encode("utf-8")
    hbytes += b" " * (-len(hbytes) % 8)
    return struct.pack("<Q", len(hbytes)) + hbytes + b"".join(chunks)


def _no_duplicates(pairs):
    d = {}
    for k, v in pairs:
        if k in d:
            raise NetworkFileError(f"header JSON has duplicate key {k!r}")
        d[k] = v
    return d


def _parse_header(data: bytes) -> tuple[dict, memoryview]:
    if len(data) < 8:
        raise NetworkFileError(f"file truncated: {len(data)} bytes, too short for the 8-byte header length")
    (hlen,) = struct.unpack("<Q", data[:8])
    # Sniff only once the length prefix is unusable: a valid header length can start with 0x80.
    if 8 + hlen > len(data) and (data[:1] == b"\x80" and data[1:2] in b"\x02\x03\x04\x05" or data[:4] == b"PK\x03\x04"):
        raise NetworkFileError("refused: data looks like a pickle / torch.save archive, not a network file")
    if hlen > MAX_HEADER_BYTES:
        raise NetworkFileError(f"header length {hlen} implausible (> {MAX_HEADER_BYTES}); file corrupt or not a network file")
    if 8 + hlen > len(data):
        raise NetworkFileError(f"file truncated: header length {hlen} runs past the end ({len(data)} bytes)")
    try:
        header = json.loads(bytes(data[8:8 + hlen]).decode("utf-8"), object_pairs_hook=_no_duplicates)
    except NetworkFileError:
        raise
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise NetworkFileError(f"header is not valid UTF-8 JSON: {exc}") from None
    if not isinstance(header, dict):
        raise NetworkFileError("header JSON is not an object")
    return header, memoryview(data)[8 + hlen:]


def _metadata(header: dict) -> dict[str, str]:
    meta = header.get("__metadata__")
    if not isinstance(meta, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items()):
        raise NetworkFileError("header __metadata__ missing or not a str -> str map")
    if meta.get("format") != FORMAT:
        raise NetworkFileError(f"wrong format {meta.get('format')!r}, expected {FORMAT!r}")
    if meta.get("format_version") not in READABLE_VERSIONS:
        raise NetworkFileError(f"unsupported format_version {meta.get('format_version')!r}, this version reads "
                               f"{', '.join(READABLE_VERSIONS)}")
    return meta


def _read_tensor(header: dict, buf: memoryview, name: str) -> np.ndarray:
    if name not in header:
        raise NetworkFileError(f"missing tensor {name!r}")
    info = header[name]
    if not isinstance(info, dict):
        raise NetworkFileError(f"tensor {name!r}: header entry is not an object")
    dtype = _DTYPES.get(info.get("dtype"))
    if dtype is None:
        raise NetworkFileError(f"tensor {name!r}: dtype {info.get('dtype')!r} not supported (F32 or F64 only)")
    shape, offs = info.get("shape"), info.get("data_offsets")
    if not (isinstance(shape, list) and all(type(s) is int and s >= 0 for s in shape)):
        raise NetworkFileError(f"tensor {name!r}: shape {shape!r} is not a list of non-negative ints")
    if not (isinstance(offs, list) and len(offs) == 2 and all(type(o) is int for o in offs)):
        raise NetworkFileError(f"tensor {name!r}: data_offsets {offs!r} malformed")
    begin, end = offs
    if not 0 <= begin <= end:
        raise NetworkFileError(f"tensor {name!r}: data_offsets [{begin}, {end}] out of bounds")
    if end > len(buf):
        raise NetworkFileError(
            f"file truncated: tensor {name!r} data_offsets end {end} past the data section ({len(buf)} bytes)")
    if end - begin != math.prod(shape) * dtype.itemsize:
        raise NetworkFileError(
            f"tensor {name!r}: data_offsets size {end - begin} bytes does not match shape {shape} x {dtype.itemsize}")
    arr = np.frombuffer(buf[begin:end], dtype=dtype).reshape(shape).astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise NetworkFileError(f"tensor {name!r} contains non-finite values (NaN or inf)")
    return arr


def network_from_bytes(data: bytes, *, expected_inputs: int | None = None,
                       expected_outputs: int | None = None) -> LipschitzMLP:
    """Parse and validate a network file's bytes; raise ``NetworkFileError`` on any defect."""
    header, buf = _parse_header(bytes(data))
    meta = _metadata(header)
    try:
        n_layers = int(meta.get("n_layers", ""))
    except ValueError:
        raise NetworkFileError(f"metadata n_layers {meta.get('n_layers')!r} is not an integer") from None
    if n_layers < 1:
        raise NetworkFileError(f"metadata n_layers {n_layers} must be >= 1")
    bound_key = "lipschitz_bound" if meta["format_version"] != "1" else "lipschitz_bound_normalised"
    units = meta.get("lipschitz_bound_units", "normalised")
    if units not in BOUND_UNITS:
        raise NetworkFileError(f"metadata lipschitz_bound_units {units!r} is not one of {BOUND_UNITS}")
    try:
        bound = float(meta.get(bound_key, ""))
    except ValueError:
        raise NetworkFileError(f"metadata {bound_key} missing or not a number") from None
    if not (math.isfinite(bound) and bound > 0):
        raise NetworkFileError(f"metadata {bound_key} {bound} must be finite and > 0")

    names = [f"layers.{i}.{p}" for i in range(n_layers) for p in ("weight", "bias")]
    names += ["input_mean", "input_std", "output_mean", "output_std"]
    extra = set(header) - set(names) - {"__metadata__"}
    if extra:
        raise NetworkFileError(f"unexpected tensors {sorted(extra)} (n_layers={n_layers})")
    t = {name: _read_tensor(header, buf, name) for name in names}

    ws = [t[f"layers.{i}.weight"] for i in range(n_layers)]
    bs = [t[f"layers.{i}.bias"] for i in range(n_layers)]
    for i, (w, b) in enumerate(zip(ws, bs)):
        if w.ndim != 2 or 0 in w.shape:
            raise NetworkFileError(f"layers.{i}.weight has shape {w.shape}, expected a non-empty 2-D matrix")
        if i > 0 and w.shape[1] != ws[i - 1].shape[0]:
            raise NetworkFileError(
                f"layer shape chain inconsistent: layers.{i}.weight takes {w.shape[1]} inputs, "
                f"layers.{i - 1} gives {ws[i - 1].shape[0]}")
        if b.shape != (w.shape[0],):
            raise NetworkFileError(f"layers.{i}.bias has shape {b.shape}, layer has {w.shape[0]} outputs")
    n_in, n_out = ws[0].shape[1], ws[-1].shape[0]
    for name, n in (("input_mean", n_in), ("input_std", n_in), ("output_mean", n_out), ("output_std", n_out)):
        if t[name].shape != (n,):
            raise NetworkFileError(f"{name} has shape {t[name].shape}, network needs ({n},)")
    for name in ("input_std", "output_std"):
        if np.any(t[name] <= 0):
            raise NetworkFileError(f"{name} has entries <= 0; a z-score std must be positive")
    if expected_inputs is not None and n_in != expected_inputs:
        raise NetworkFileError(f"network takes {n_in} inputs, expected {expected_inputs}")
    if expected_outputs is not None and n_out != expected_outputs:
        raise NetworkFileError(f"network gives {n_out} outputs, expected {expected_outputs}")

    own_meta = {k: v for k, v in meta.items() if k not in RESERVED_KEYS}
    try:
        net = LipschitzMLP(tuple(ws), tuple(bs), t["input_mean"], t["input_std"],
                           t["output_mean"], t["output_std"], bound, own_meta, units)
        net.feature_set  # noqa: B018 - a file must say inputs this version can build
        net.thrust_lag  # noqa: B018
    except FeatureSetError as exc:
        raise NetworkFileError(f"inputs refused: {exc}") from None
    except ValueError as exc:  # checks above should have caught everything; keep the gate closed
        raise NetworkFileError(f"network invalid: {exc}") from None
    cert = net.certified_lipschitz()
    if cert > bound * (1.0 + CERT_RTOL):
        raise NetworkFileError(
            f"certificate fails: exact spectral-norm product {cert!r} exceeds stated bound "
            f"{bound!r} ({units})")
    return net


def save_network(path: str | os.PathLike, net: LipschitzMLP) -> None:
    """Write atomically: temp file in the same directory, fsync, ``os.replace``."""
    path = os.fspath(path)
    data = network_to_bytes(net)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".safetensors", dir=os.path.dirname(path) or ".")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def load_network(path: str | os.PathLike, *, expected_inputs: int | None = None,
                 expected_outputs: int | None = None) -> LipschitzMLP:
    """Read and validate a network file (see ``network_from_bytes``)."""
    with open(path, "rb") as f:
        data = f.read()
    return network_from_bytes(data, expected_inputs=expected_inputs, expected_outputs=expected_outputs)
