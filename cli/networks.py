"""``neso networks list``: the networks the estimator can fly — the shipped ones in ``networks/`` and
the trained ones in the registry — with their bound, validation loss and small-gain verdict."""
from __future__ import annotations

import json
from pathlib import Path


def add_parser(subparsers) -> None:
    from services.registry import DEFAULT_ROOT

    p = subparsers.add_parser("networks", help="the shipped networks and the network registry")
    sub = p.add_subparsers(dest="networks_command", required=True)
    lp = sub.add_parser("list", help="shipped networks (networks/), then every stored one (registry), oldest first")
    lp.add_argument("--shipped", default="networks", help="folder of the shipped networks (default networks)")
    lp.add_argument("--registry", default=DEFAULT_ROOT, help="network registry root (default %(default)s)")
    lp.add_argument("--vehicle", default=None, help="only this vehicle's registry networks")
    lp.add_argument("--json", action="store_true")


def _num(v, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def shipped_rows(folder: str, registry: Path) -> list[dict]:
    """One row per network file under ``folder`` (the registry's excepted), shaped like a registry
    row, ``where: shipped``; the small-gain verdict at the trainer's z gains (the registry's
    convention), at the network's certified physical bound."""
    from neso.certificate import LoopPlant
    from neso.control import ControlConfig
    from neso.netfile import NetworkFileError, load_network
    from flight.estimator import DEFAULT_NETWORK, network_certificate, shipped
    from services.trainer import TrainerConfig

    gains = TrainerConfig()
    plant = LoopPlant.of(ControlConfig())
    flown_by_default = Path(shipped(DEFAULT_NETWORK)).resolve()
    rows = []
    for path in sorted(Path(folder).rglob("*.safetensors")):
        if path.resolve().is_relative_to(registry.resolve()):
            continue
        try:
            net = load_network(path)
        except NetworkFileError as exc:
            rows.append({"where": "shipped", "id": path.stem, "path": str(path), "error": str(exc)})
            continue
        meta = net.metadata
        certified = net.certified_lipschitz_physical()
        cert = network_certificate(net, gains.kp, gains.kd, gains.omega_o_rps, plant)
        val = meta.get("val_loss")
        rows.append({"where": "shipped", "id": meta.get("id", path.stem), "vehicle": meta.get("vehicle", ""),
                     "label": meta.get("training_data", "").split(":")[0], "parent": "" if meta.get("warm_start", "no") == "no" else meta["warm_start"],
                     "training_data": meta.get("training_data", ""), "lipschitz_norm": net.lipschitz_bound,
                     "lipschitz_phys": net.lipschitz_bound_physical(), "certified_phys": certified,
                     "val_loss": float(val) if val else None, **net.learned, "certificate_holds": cert.holds,
                     "certificate": cert.to_dict(), "feature_set": net.feature_set.key,
                     "flown_by_default": path.resolve() == flown_by_default, "path": str(path)})
    return rows


def _slopes_text(slopes: dict) -> str:
    return " ".join(f"{k.split('_')[0]}{v:+.2f}" for k, v in slopes.items()) or "—"


def _gain_text(change: dict | None) -> str:
    return "—" if not change else f"{change['dkp']:+.2f} {change['dkd']:+.2f}"


def run(args) -> int:
    from services.registry import entries

    rows = shipped_rows(args.shipped, Path(args.registry)) + [dict(e.row(), where="registry")
                                         for e in entries(args.registry, args.vehicle)]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    if not rows:
        print(f"no networks in {args.shipped} or {args.registry}")
        return 0
    print(f"{'where':8} {'id':44} {'label':12} {'L_N norm':>8} {'certified':>9} {'val loss':>9} {'vs mean':>7} "
          f"{'small-gain':>10}  {'slopes ∂f_N/∂input':34} {'Δk_p Δk_d':11} parent / trained on")
    for r in rows:
        if "error" in r:
            print(f"{r['where']:8} {r['id']:44} UNREADABLE: {r['error']}")
            continue
        cert = {True: "holds", False: "no", None: "—"}[r["certificate_holds"]]
        source = r.get("training_data") or ", ".join(p.rsplit("/", 1)[-1] for p in r.get("recordings", []))
        mark = " *" if r.get("flown_by_default") else ""
        print(f"{r['where']:8} {r['id'] + mark:44} {r['label'][:12]:12} {_num(r['lipschitz_norm'], '8.3g')} "
              f"{_num(r.get('certified_phys'), '9.4g')} {_num(r['val_loss'], '9.4g')} "
              f"{_num(r.get('val_loss_vs_mean'), '7.3f')} {cert:>10}  {_slopes_text(r.get('slopes') or {}):34} "
              f"{_gain_text(r.get('gain_change')):11} {r['parent'] or '—'} / {source or '—'}")
    if not any(r["where"] == "registry" for r in rows):
        print(f"(registry {args.registry}: empty — `neso train` stores there)")
    if any(r.get("flown_by_default") for r in rows):
        print("* flown by the estimator by default (--network); certified: the physical L_N ((m/s²)/unit z) the network provably meets in all its inputs; small-gain: the role certificate at the trainer's "
              "z gains for the network's certified slope in its state inputs; vs mean: validation loss over that of predicting "
              "the mean (< 1: it learned something); slopes: mean physical ∂f_N/∂input over its training inputs; "
              "Δk_p Δk_d: those on p_z and v_z as a change of the z gains (the controller subtracts f_N, e = z* − z: "
              "+∂f_N/∂p_z is +k_p, 1/s², +∂f_N/∂v_z is +k_d, 1/s)")
    return 0
