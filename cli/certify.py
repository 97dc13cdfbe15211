"""``neso certify``: the small-gain stability certificate of the paper's Section IV.

Exit code 0 when the certificate holds for the chosen method (``both``: the tight one; ``all``, the default:
the LMI one, the tightest), 1 when it does not.

``--json`` output: the chosen method's fields at top level (at least ``holds``, ``alpha_e``, ``alpha_o``,
``ultimate_bound``, ``max_certified_lipschitz``); with ``--method both`` the top level is the TIGHT certificate
and both full results are nested under ``"literal"`` and ``"tight"``; with ``--method all`` (default) the top level
is the LMI certificate and all three are nested under their names. Non-finite numbers are ``null``.
Units: ``L_N`` in (m/s²) per unit of the mixed-SI network input z (physical, not normalised); bounds on
``‖E‖``, ``E = [e, ė, x̃1, x̃2, f̃]`` in mixed SI (m, m/s, m, m/s, m/s²).
"""
from __future__ import annotations

import argparse
import json
import math

_DEFAULTS = dict(L1=5.0, Lu=20.0, ref_vel_max=0.5, ref_acc_max=1.0)


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``certify`` on an ``argparse`` sub-parsers object and return its parser."""
    p = subparsers.add_parser(
        "certify",
        help="check the Neural-ESO small-gain stability certificate (paper Lemma 1, Theorem 1)",
        description="Small-gain certificate for given PD gains, observer bandwidth and network Lipschitz "
        "constant. L_N is the PHYSICAL Lipschitz constant ((m/s^2) per unit of mixed-SI z); a normalised "
        "bound converts as L_phys = L_norm * sigma_y / min(sigma_z).",
    )
    p.add_argument("--kp", type=float, required=True, help="proportional gain, 1/s^2")
    p.add_argument("--kd", type=float, required=True, help="derivative gain, 1/s")
    p.add_argument("--omega-o", type=float, required=True, help="observer bandwidth, rad/s")
    p.add_argument("--lipschitz", type=float, required=True, help="network Lipschitz constant L_N (physical)")
    p.add_argument("--L1", type=float, default=_DEFAULTS["L1"], help="bound on |df/dt|, m/s^3 (default %(default)s)")
    p.add_argument("--Lu", type=float, default=_DEFAULTS["Lu"], help="bound on |du/dt|, z-units/s (default %(default)s)")
    p.add_argument("--ref-vel-max", type=float, default=_DEFAULTS["ref_vel_max"], help="|q*'| bound, m/s (default %(default)s)")
    p.add_argument("--ref-acc-max", type=float, default=_DEFAULTS["ref_acc_max"], help="|q*''| bound, m/s^2 (default %(default)s)")
    p.add_argument("--n-axes", type=int, default=1, help="identical axes (does not change the result)")
    p.add_argument("--lambda-c-rule", choices=("corrected", "paper"), default="corrected",
                   help="lambda_c: 'corrected' sqrt(kp^2+(kd+1)^2) covers the |de/dt| term the paper's Lemma 1 "
                   "drops; 'paper' sqrt(kp^2+kd^2) as printed (default %(default)s)")
    p.add_argument("--method", choices=("literal", "tight", "lmi", "both", "all"), default="all",
                   help="literal: paper as written (Q=I, Young splits); tight: optimised scalings/weights; "
                   "lmi: quadratic V=E'PE by SDP (cvxpy + Clarabel), re-verified in numpy (all: same assumptions); "
                   "both: literal and tight, verdict from tight; all (default): the three, verdict from lmi")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)
    return p


def _inputs(args):
    from neso.certificate import CertificateInputs

    return CertificateInputs(
        kp=args.kp, kd=args.kd, omega_o=args.omega_o, lipschitz=args.lipschitz, n_axes=args.n_axes,
        L_1=args.L1, L_u=args.Lu, ref_vel_max=args.ref_vel_max, ref_acc_max=args.ref_acc_max,
        lambda_c_rule=args.lambda_c_rule,
    )


def _fmt(v: float) -> str:
    return "inf" if not math.isfinite(v) else f"{v:.6g}"


def _text(res) -> list[str]:
    lines = [
        f"[{res.method}] {'HOLDS' if res.holds else 'FAILS'}",
        f"  alpha_e = {_fmt(res.alpha_e)}   alpha_o = {_fmt(res.alpha_o)}   (margins; > 0 iff holds)",
        f"  ultimate bound (V' < 0 outside) ||E|| <= {_fmt(res.ultimate_bound)}   "
        f"eventual (sublevel set) ||E|| <= {_fmt(res.ultimate_bound_sublevel)}   [mixed SI: m, m/s, m/s^2]",
        f"  max certified L_N = {_fmt(res.max_certified_lipschitz)}   [(m/s^2) per unit z, physical]",
    ]
    if res.method == "literal" and res.holds:
        lines.append(f"  delta_e = {_fmt(res.delta_e)}  delta_o = {_fmt(res.delta_o)}  delta_c = {_fmt(res.delta_c)}"
                     f"  C_o = {_fmt(res.C_o)}")
    if res.method == "tight":
        lines.append(f"  observer scaling T_o = {[float(f'{t:.4g}') for t in res.scale_obs]}  "
                     f"weight s = {res.weight_s:.4g}")
    if res.method == "lmi" and res.holds:
        lines.append(f"  P {res.structure}, V' <= -alpha V + mu C_f^2: alpha = {_fmt(res.alpha)} 1/s, "
                     f"mu = {_fmt(res.mu)}, re-verified in numpy")
    return lines


def run(args) -> int:
    """Compute, print (text or ``--json``) and return 0 if the certificate holds, 1 otherwise."""
    from neso.certificate import certify_lmi, certify_literal, certify_tight

    try:
        inputs = _inputs(args)
    except ValueError as exc:
        print(f"neso certify: {exc}")
        return 2
    results = {}
    if args.method in ("literal", "both", "all"):
        results["literal"] = certify_literal(inputs)
    if args.method in ("tight", "both", "all"):
        results["tight"] = certify_tight(inputs)
    if args.method in ("lmi", "all"):
        results["lmi"] = certify_lmi(inputs)
    main = results[{"both": "tight", "all": "lmi"}.get(args.method, args.method)]

    if args.json:
        out = main.to_json_dict()
        if args.method in ("both", "all"):
            out.update({name: res.to_json_dict() for name, res in results.items()})
        out["inputs"] = {
            "kp": inputs.kp, "kd": inputs.kd, "omega_o": inputs.omega_o, "lipschitz": inputs.lipschitz,
            "L1": inputs.L_1, "Lu": inputs.L_u, "ref_vel_max": inputs.ref_vel_max,
            "ref_acc_max": inputs.ref_acc_max, "n_axes": inputs.n_axes, "lambda_c_rule": inputs.lambda_c_rule,
        }
        out["method_requested"] = args.method
        print(json.dumps(out, indent=2))
    else:
        print(f"Neural-ESO certificate: kp={inputs.kp:g} 1/s^2, kd={inputs.kd:g} 1/s, omega_o={inputs.omega_o:g} "
              f"rad/s, L_N={inputs.lipschitz:g} (m/s^2)/unit z; L1={inputs.L_1:g} m/s^3, Lu={inputs.L_u:g}, "
              f"C_f={inputs.C_f:.4g} m/s^3, lambda_c={inputs.lambda_c:.4g} ({inputs.lambda_c_rule})")
        for res in results.values():
            print("\n".join(_text(res)))
        if args.method in ("both", "all"):
            print(f"verdict ({main.method}): {'HOLDS' if main.holds else 'FAILS'}")
    return 0 if main.holds else 1
