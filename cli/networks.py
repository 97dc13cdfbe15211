"""``neso networks list``: what the network registry holds (id, vehicle, label, bound, val loss, certificate)."""
from __future__ import annotations

import json


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("networks", help="the network registry")
    sub = p.add_subparsers(dest="networks_command", required=True)
    lp = sub.add_parser("list", help="every stored network, oldest first")
    lp.add_argument("--registry", default="networks/registry")
    lp.add_argument("--vehicle", default=None, help="only this vehicle's networks")
    lp.add_argument("--json", action="store_true")


def _num(v, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def run(args) -> int:
    from services.registry import entries

    rows = [e.row() for e in entries(args.registry, args.vehicle)]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    if not rows:
        print(f"no networks in {args.registry}")
        return 0
    print(f"{'id':44} {'label':5} {'L_N norm':>8} {'L_N phys':>9} {'val loss':>9} {'small-gain':>10}  parent / recordings")
    for r in rows:
        cert = {True: "holds", False: "no", None: "—"}[r["certificate_holds"]]
        recs = ", ".join(p.rsplit("/", 1)[-1] for p in r["recordings"])
        print(f"{r['id']:44} {r['label']:5} {_num(r['lipschitz_norm'], '8.3g')} {_num(r['lipschitz_phys'], '9.4g')} "
              f"{_num(r['val_loss'], '9.4g')} {cert:>10}  {r['parent'] or '—'} / {recs}")
    return 0
