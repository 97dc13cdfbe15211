"""The network registry on disk: ``<root>/<vehicle>/<id>.safetensors`` plus a ``<id>.json`` sidecar.

The network file is self-describing (its safetensors metadata carries everything below, so a
file copied out of the registry still says where it came from); the sidecar repeats it as JSON
so listing the registry does not parse tensors. Fields: ``id``, ``vehicle``, ``label`` (``eso``
or ``tdr``), ``parent`` (the network it was warm-started from, ``""`` if none), ``recordings``
(the ``.rrd`` files it was trained on), ``created`` (UTC, ISO 8601), ``lipschitz_norm`` /
``lipschitz_phys`` (the bound, normalised and (m/s²) per unit z), ``certified_norm`` /
``certified_phys`` (exact SVD product, same units), ``val_loss`` (z-scored MSE) and
``val_loss_physical`` ((m/s²)²), ``val_loss_vs_mean``, ``slopes`` (mean physical ∂f_N/∂input) and
``gain_change`` (those on p_z and v_z as a change of the z gains, ``dkp``/``dkd``:
:func:`neso.learning.equivalent_gains`), ``feature_set``, ``bound_units``, ``certificate``: the stability
certificate for the z gains and observer bandwidth flown at the network's certified physical L_N
(:meth:`neso.certificate.FlightCertificate.to_dict`: ``holds``, ``lipschitz_phys``,
``max_certified``, ``margin``, the gains, ``text``), and ``predicted``: the closed-loop prediction
on the recorded flights (``rmse_active_cm``, ``rmse_candidate_cm``, ``change``, ``rmse_pdeso_cm``,
``change_vs_pdeso``, ``rmse_gain_only_cm``, ``gain_only``, ``split``: :func:`services.trainer.predict_closed_loop`;
empty if none).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from neso.netfile import network_to_bytes, save_network
from neso.network import LipschitzMLP

DEFAULT_ROOT = "networks/registry"


@dataclass(frozen=True)
class Entry:
    """One stored network (see module docstring); ``path`` is the network file."""

    id: str
    vehicle: str
    path: str
    info: dict

    def row(self) -> dict:
        i = self.info
        return {"id": self.id, "vehicle": self.vehicle, "label": i.get("label", ""), "parent": i.get("parent", ""),
                "created": i.get("created", ""), "lipschitz_norm": i.get("lipschitz_norm"),
                "lipschitz_phys": i.get("lipschitz_phys"), "certified_phys": i.get("certified_phys"),
                "val_loss": i.get("val_loss"), "val_loss_vs_mean": i.get("val_loss_vs_mean"),
                "slopes": i.get("slopes") or {}, "gain_change": i.get("gain_change"),
                "certificate_holds": (i.get("certificate") or {}).get("holds"),
                "feature_set": i.get("feature_set", ""), "predicted_change": (i.get("predicted") or {}).get("change"),
                "recordings": i.get("recordings", []), "path": self.path}


def new_id(vehicle: str, label: str, net: LipschitzMLP, now_s: float | None = None) -> str:
    """``<vehicle>-<label>-<UTC yyyymmddThhmmss>-<6 hex of the weights>``: sortable and unique."""
    stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(time.time() if now_s is None else now_s))
    digest = hashlib.sha256(network_to_bytes(net)).hexdigest()[:6]
    return f"{vehicle}-{label}-{stamp}-{digest}"


def store(net: LipschitzMLP, *, root: str | os.PathLike = DEFAULT_ROOT, vehicle: str, label: str, parent: str,
          recordings: list[str], certificate: dict, predicted: dict | None = None) -> Entry:
    """Write ``net`` with its provenance into the registry and return its entry."""
    net_id = new_id(vehicle, label, net)
    info = {
        "id": net_id, "vehicle": vehicle, "label": label, "parent": parent, "recordings": list(recordings),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "lipschitz_norm": net.lipschitz_bound, "lipschitz_phys": net.lipschitz_bound_physical(),
        "certified_norm": net.certified_lipschitz_normalised(), "certified_phys": net.certified_lipschitz_physical(),
        "val_loss": float(net.metadata.get("val_loss", "nan")),
        "val_loss_physical": float(net.metadata.get("val_loss_physical", "nan")),
        **net.learned,
        "certificate": certificate, "feature_set": net.feature_set.key, "bound_units": net.bound_units,
        "predicted": dict(predicted or {}),
    }
    meta = dict(net.metadata)
    meta.update({k: (v if isinstance(v, str) else json.dumps(v)) for k, v in info.items()
                 if k not in ("lipschitz_norm", "lipschitz_phys", "certified_norm", "certified_phys", "feature_set",
                              "bound_units")})
    meta["training_data"] = f"{label}:" + ",".join(Path(r).name for r in recordings)
    stored = LipschitzMLP(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                          net.lipschitz_bound, meta, net.bound_units)
    folder = Path(root) / vehicle
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{net_id}.safetensors"
    save_network(path, stored)
    _write_json(folder / f"{net_id}.json", {k: _json_safe(v) for k, v in info.items()})
    return Entry(net_id, vehicle, str(path), info)


def _json_safe(v):
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _write_json(path: Path, data: dict) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".json", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)


def entries(root: str | os.PathLike = DEFAULT_ROOT, vehicle: str | None = None) -> list[Entry]:
    """Every stored network (oldest first), optionally of one vehicle; unreadable sidecars are skipped."""
    out = []
    base = Path(root)
    if not base.is_dir():
        return out
    for sidecar in sorted(base.glob("*/*.json")):
        if vehicle is not None and sidecar.parent.name != vehicle:
            continue
        try:
            info = json.loads(sidecar.read_text())
        except (OSError, ValueError):
            continue
        path = sidecar.with_suffix(".safetensors")
        if path.is_file():
            out.append(Entry(info.get("id", sidecar.stem), sidecar.parent.name, str(path), info))
    return sorted(out, key=lambda e: (e.info.get("created", ""), e.id))
