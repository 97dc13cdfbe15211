"""``neso certify``: the small-gain stability certificate of the paper's Section IV.

Exit code 0 when the certificate holds for the chosen method (``both``: the tight one; ``all``, the default:
the role certificate, the tightest and the one the services fly by), 1 when it does not, 2 for bad input (a
network file that cannot be read, invalid gains).

Methods: ``literal``, ``tight`` and ``lmi`` take the paper's Lemma 1 (the whole input z through ``‖ż‖``);
``roles`` is the verdict the services fly by (:func:`neso.certificate.flight_certificate`): every input in its
role — the state inputs (p_z, v_z) in the loop gain, the thrust and attitude also in the loop through the
controller's output (its gain must stay below 1), what the vehicle's limits bound in the constant — with the
eventual |e_z| bound in cm against PD+ESO's (at most ``max_bound_ratio`` ×) and the mass a thrust input was made
for. Its JSON's top level carries one ``margin`` (the state slope's headroom the services act on) and ``parts``
(state, exogenous, loop) beside it.

``--network FILE|default``: the L_N certified is the network's exact physical Lipschitz constant (the
SVD product of its weights with the z-scores folded in): of all its inputs for Lemma 1's methods, of each role's
inputs for ``roles``; ``default`` is the network ``neso up`` flies. The gains default to the controller's (z axis) and the observer bandwidth to the
estimator's.

``--frontier``: the largest certified L_N of every method over a grid of k_p, k_d, ω_o (a table; ``--json``;
``--plot FILE.png``): how gains and budget are chosen together.

``--json`` output: the chosen method's fields at top level (at least ``holds``, ``alpha_e``, ``alpha_o``,
``ultimate_bound``, ``max_certified_lipschitz``); with ``--method both`` the top level is the TIGHT certificate
and both full results are nested under ``"literal"`` and ``"tight"``; with ``--method all`` (default) the top level
is the LMI certificate and all three are nested under their names; with ``--network`` also ``network`` (path,
id, inputs, both bounds). Non-finite numbers are ``null``.
Units: ``L_N`` in (m/s²) per unit of the mixed-SI network input z (physical, not normalised); bounds on
``‖E‖``, ``E = [e, ė, x̃1, x̃2, f̃]`` in mixed SI (m, m/s, m, m/s, m/s²).
"""
from __future__ import annotations

import argparse
import json
import math

def _constants() -> dict:
    from neso.certificate.core import L1_MPS3, LU_PER_S, REF_ACC_MAX_MPS2, REF_VEL_MAX_MPS

    return dict(L1=L1_MPS3, Lu=LU_PER_S, ref_vel_max=REF_VEL_MAX_MPS, ref_acc_max=REF_ACC_MAX_MPS2)


def _flight_defaults() -> tuple[float, float, float, str]:
    """(k_p, k_d of z, ω_o, default network) as the services start: their config dataclasses."""
    from neso.control import ControlConfig
    from flight.estimator import EstimatorConfig

    c, e = ControlConfig(), EstimatorConfig()
    return c.kp[2], c.kd[2], e.omega_o_rps, e.network


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``certify`` on an ``argparse`` sub-parsers object and return its parser."""
    p = subparsers.add_parser(
        "certify",
        help="check the Neural-ESO small-gain stability certificate (paper Lemma 1, Theorem 1)",
        description="Small-gain certificate for given PD gains, observer bandwidth and network Lipschitz "
        "constant. L_N is the PHYSICAL Lipschitz constant ((m/s^2) per unit of mixed-SI z); a normalised "
        "bound converts as L_phys = L_norm * sigma_y / min(sigma_z).",
        epilog="exit status: 0 the certificate holds, 1 it fails (for scripts: `neso certify ... && fly`), "
        "2 the input is refused (e.g. an unreadable network file).",
    )
    from neso.types import VehicleModel

    kp, kd, omega_o, _ = _flight_defaults()
    p.add_argument("--kp", type=_numbers, default=(kp,), help="proportional gain, 1/s^2 (default: the controller's z, "
                   f"{kp:g}; --frontier: comma-separated, default {','.join(map(str, FRONTIER_KP))})")
    p.add_argument("--kd", type=_numbers, default=(kd,), help="derivative gain, 1/s (default: the controller's z, "
                   f"{kd:g}; --frontier: default {','.join(map(str, FRONTIER_KD))})")
    p.add_argument("--omega-o", type=_numbers, default=(omega_o,), help="observer bandwidth, rad/s (default "
                   f"{omega_o:g}; --frontier: default {','.join(map(str, FRONTIER_OMEGA))})")
    p.add_argument("--plot", default=None, metavar="FILE.png", help="with --frontier: a plot of the frontier")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--lipschitz", type=float, help="network Lipschitz constant L_N (physical; for roles: in the "
                      "state inputs of a network with no other input)")
    what.add_argument("--frontier", action="store_true", help="the largest certified L_N of every method over a "
                      "grid of gains (--kp/--kd/--omega-o lists with commas)")
    what.add_argument("--network", metavar="FILE|default",
                      help="certify this network file's exact physical L_N ('default': the network neso up flies)")
    constants = _constants()
    p.add_argument("--L1", type=float, default=constants["L1"], help="bound on |df/dt|, m/s^3 (default %(default)s)")
    p.add_argument("--Lu", type=float, default=constants["Lu"], help="bound on |du/dt|, z-units/s (default %(default)s)")
    p.add_argument("--ref-vel-max", type=float, default=constants["ref_vel_max"], help="|q*'| bound, m/s (default %(default)s)")
    p.add_argument("--ref-acc-max", type=float, default=constants["ref_acc_max"], help="|q*''| bound, m/s^2 (default %(default)s)")
    p.add_argument("--n-axes", type=int, default=1, help="identical axes (does not change the result)")
    p.add_argument("--mass-kg", type=float, default=VehicleModel().mass_kg,
                   help="the vehicle's mass (roles: the loop through a thrust input, and the mass a network with one "
                        "was made for; default %(default)s)")
    p.add_argument("--lambda-c-rule", choices=("corrected", "paper"), default="corrected",
                   help="lambda_c: 'corrected' sqrt(kp^2+(kd+1)^2) covers the |de/dt| term the paper's Lemma 1 "
                   "drops; 'paper' sqrt(kp^2+kd^2) as printed (default %(default)s)")
    p.add_argument("--method", choices=("literal", "tight", "lmi", "roles", "both", "all"), default="all",
                   help="literal: paper as written (Q=I, Young splits); tight: optimised scalings/weights; "
                   "lmi: quadratic V=E'PE by SDP (cvxpy + Clarabel), re-verified in numpy (these three: Lemma 1); "
                   "roles: the state inputs in the loop gain, the others in the constant (SDP, re-verified); "
                   "both: literal and tight, verdict from tight; all (default): the four, verdict from roles")
    p.add_argument("--json", action="store_true", help="print JSON instead of text: the verdict, each method's "
                   "figures, the inputs (compact)")
    p.add_argument("--verbose", action="store_true", help="with --json: every method's matrices and terms too")
    p.set_defaults(func=run)
    return p


FRONTIER_KP = (4.0, 10.0, 20.0)
FRONTIER_KD = (3.0, 6.0, 10.0)
FRONTIER_OMEGA = (10.0, 15.0, 20.0, 30.0)


def _numbers(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or a comma-separated list of numbers: {text!r}") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"gains must be positive and finite, got {text!r}")
    return values


def _network(args) -> tuple[float, dict]:
    """(L_N physical, what the JSON says of the network); ValueError naming why a file is refused."""
    from neso.netfile import NetworkFileError, load_network

    from flight.estimator import shipped

    path = shipped(_flight_defaults()[3] if args.network == "default" else args.network)
    try:
        net = load_network(path)
    except FileNotFoundError:
        raise ValueError(f"no such network file: {path}") from None
    except (OSError, NetworkFileError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    from neso.certificate import NetworkSlopes

    lip = net.certified_lipschitz_physical()
    exo = tuple(i for i in range(net.n_inputs) if i not in net.state_columns)
    return lip, {"path": path, "id": net.metadata.get("id", ""), "feature_set": net.feature_set.key,
                 "slopes": NetworkSlopes.of(net).to_dict(),
                 "bound_units": net.bound_units, "lipschitz_bound": net.lipschitz_bound,
                 "certified_lipschitz_physical": lip,
                 "certified_lipschitz_state": net.certified_lipschitz_state(),
                 "certified_lipschitz_exogenous": net.certified_lipschitz_columns(exo) if exo else 0.0,
                 "certified_lipschitz_normalised": net.certified_lipschitz_normalised()}


def _inputs(args, lipschitz: float):
    from neso.certificate import CertificateInputs

    return CertificateInputs(
        kp=args.kp[0], kd=args.kd[0], omega_o=args.omega_o[0], lipschitz=lipschitz, n_axes=args.n_axes,
        L_1=args.L1, L_u=args.Lu, ref_vel_max=args.ref_vel_max, ref_acc_max=args.ref_acc_max,
        lambda_c_rule=args.lambda_c_rule,
    )


def _fmt(v: float) -> str:
    return "inf" if not math.isfinite(v) else f"{v:.6g}"


def _text(res) -> list[str]:
    if isinstance(res, _Flight):
        c = res.cert
        s = c.slopes
        lines = [f"[roles] {'HOLDS' if c.holds else 'FAILS'}  (what the services fly by)",
                 f"  slopes by role [(m/s^2) per unit]: state {_fmt(s.state)} (max certified {_fmt(c.max_certified)} at "
                 f"this loop gain, margin {_fmt(c.margin)}), thrust {_fmt(s.thrust)} /N, attitude {_fmt(s.attitude)} "
                 f"/rad, speed {_fmt(s.speed)} /(m/s)",
                 f"  loop through the controller's output: gain {_fmt(c.loop_gain)} (< 1 needed); exogenous rates move "
                 f"f_N by {_fmt(c.exogenous_rate_mps3)} m/s^3",
                 f"  eventual |e_z| <= {_fmt(c.bound_cm)} cm over the reference envelope (PD+ESO: {_fmt(c.pdeso_bound_cm)} "
                 f"cm; ratio {_fmt(c.bound_ratio)}, at most {c.policy.max_bound_ratio:g}); hover: "
                 f"{_fmt(res.hover[0])} cm (PD+ESO {_fmt(res.hover[1])} cm); re-verified in numpy"]
        lines += [f"  refused: {r}" for r in c.reasons]
        return lines
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


VERDICT = ("holds", "method", "max_certified_lipschitz", "ultimate_bound")  # the top level of the JSON


class _Flight:
    """The role certificate as the services decide with it (:func:`neso.certificate.flight_certificate`), for the
    CLI's table and JSON: ``cert`` and its bounds at hover ``(network's, PD+ESO's)`` in cm."""

    method = "roles"

    def __init__(self, cert) -> None:
        from neso.certificate import ReferenceBounds

        self.cert = cert
        self.holds = cert.holds
        self.hover = cert.bound_for_cm(ReferenceBounds())

    def to_json_dict(self) -> dict:
        c = self.cert
        out = dict(c.to_dict(), method="roles", max_certified_lipschitz=c.max_certified,
                   ultimate_bound=c.role.to_json_dict()["ultimate_bound"], alpha_e=c.role.to_json_dict()["alpha_e"],
                   alpha_o=c.role.to_json_dict()["alpha_o"],
                   hover_bound_cm=self.hover[0] if math.isfinite(self.hover[0]) else None,
                   hover_pdeso_bound_cm=self.hover[1] if math.isfinite(self.hover[1]) else None,
                   role=c.role.to_json_dict())
        out["parts"] = {"state": c.slopes.state, "exogenous": {"thrust": c.slopes.thrust, "attitude": c.slopes.attitude,
                                                               "speed": c.slopes.speed,
                                                               "rate_mps3": c.exogenous_rate_mps3},
                        "loop_gain": c.loop_gain}
        out["units"] = {"slopes": "(m/s^2) per unit of the input (m, m/s; N; rad; m/s)", "bound_cm": "eventual |e_z|, cm",
                        "loop_gain": "dimensionless, < 1 needed", "rate_mps3": "m/s^3",
                        "ultimate_bound": "Euclidean norm of E in mixed SI"}
        return out
FIGURES = ("holds", "max_certified_lipschitz", "alpha_e", "alpha_o", "ultimate_bound")  # each method's, compact


def _json(args, inputs, results: dict, main, network: dict | None) -> dict:
    """The verdict (its method's holds, largest certified L_N, margin, ultimate bound) at the top level; under
    ``methods`` each method's figures, or with ``--verbose`` everything it computed (matrices, terms, notes);
    the inputs; the network when one was given."""
    full = {name: res.to_json_dict() for name, res in results.items()}
    main_name = next(name for name, res in results.items() if res is main)
    out = {k: full[main_name][k] for k in VERDICT}
    if isinstance(main, _Flight):  # one margin, the one the services act on; each part beside it
        out.update({k: full[main_name][k] for k in ("margin", "parts", "bound_cm", "pdeso_bound_cm", "bound_ratio",
                                                      "max_bound_ratio", "hover_bound_cm", "hover_pdeso_bound_cm",
                                                      "reasons", "text")})
    else:
        out["margin"] = (None if out["max_certified_lipschitz"] is None
                         else out["max_certified_lipschitz"] - inputs.lipschitz)
    out["methods"] = full if args.verbose else {name: {k: d[k] for k in FIGURES} for name, d in full.items()}
    out["inputs"] = {
        "kp": inputs.kp, "kd": inputs.kd, "omega_o": inputs.omega_o, "lipschitz": inputs.lipschitz,
        "L1": inputs.L_1, "Lu": inputs.L_u, "ref_vel_max": inputs.ref_vel_max,
        "ref_acc_max": inputs.ref_acc_max, "n_axes": inputs.n_axes, "lambda_c_rule": inputs.lambda_c_rule,
        "method": args.method,
    }
    out["units"] = full[main_name]["units"]
    if network is not None:
        out["network"] = network
    return out


def _roles(args, inputs, network: dict | None) -> _Flight:
    from neso.certificate import LoopPlant, NetworkSlopes, flight_certificate
    from neso.control import ControlConfig
    from neso.types import VehicleModel

    slopes = NetworkSlopes.from_dict(network["slopes"]) if network else NetworkSlopes(inputs.lipschitz)
    plant = LoopPlant.of(ControlConfig(vehicle=VehicleModel(mass_kg=args.mass_kg)))
    return _Flight(flight_certificate(slopes, kp=inputs.kp, kd=inputs.kd, omega_o=inputs.omega_o, plant=plant))


def frontier_rows(kps, kds, omegas) -> list[dict]:
    """One row per gain set: the largest certified L_N ((m/s²) per unit z) of every method and the role
    certificate's exact ``1/‖G‖_∞``."""
    from neso.certificate import (CertificateInputs, certify_literal, certify_tight, max_certified_lipschitz_best,
                                  max_certified_state_lipschitz, max_certified_state_lipschitz_verified)

    rows = []
    for kp in kps:
        for kd in kds:
            for w in omegas:
                inputs = CertificateInputs(kp=kp, kd=kd, omega_o=w, lipschitz=0.0)
                rows.append({"kp": kp, "kd": kd, "omega_o": w,
                             "literal": certify_literal(inputs).max_certified_lipschitz,
                             "tight": certify_tight(inputs, optimise_bound=False).max_certified_lipschitz,
                             "lmi": max_certified_lipschitz_best(kp, kd, w),
                             "roles": max_certified_state_lipschitz_verified(kp, kd, w),
                             "roles_exact": max_certified_state_lipschitz(kp, kd, w)})
    return rows


def _frontier(args) -> int:
    from neso.learning import DEFAULT_RECIPE, RECIPES

    kps = args.kp if len(args.kp) > 1 or args.kp != (_flight_defaults()[0],) else FRONTIER_KP
    kds = args.kd if len(args.kd) > 1 or args.kd != (_flight_defaults()[1],) else FRONTIER_KD
    omegas = args.omega_o if len(args.omega_o) > 1 or args.omega_o != (_flight_defaults()[2],) else FRONTIER_OMEGA
    rows = frontier_rows(kps, kds, omegas)
    fraction = RECIPES[DEFAULT_RECIPE].certified_fraction
    if args.json:
        print(json.dumps({"rows": rows, "trainer_fraction": fraction,
                          "units": "(m/s^2) per unit z, physical; roles: in the state inputs"}, indent=1))
    else:
        print(f"largest certified L_N, (m/s^2) per unit z (the trainer spends {fraction:g} × roles):")
        print(f"{'kp':>5} {'kd':>5} {'ω_o':>5} {'literal':>9} {'tight':>8} {'lmi':>8} {'roles':>8} {'roles/lmi':>9}")
        for r in rows:
            print(f"{r['kp']:5g} {r['kd']:5g} {r['omega_o']:5g} {r['literal']:9.4g} {r['tight']:8.4g} "
                  f"{r['lmi']:8.4g} {r['roles']:8.4g} {r['roles'] / r['lmi']:9.2f}")
    if args.plot:
        _plot_frontier(rows, args.plot)
        if not args.json:
            print(f"plot: {args.plot}")
    return 0


def _plot_frontier(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kps = sorted({r["kp"] for r in rows})
    fig, axes = plt.subplots(1, len(kps), figsize=(4.2 * len(kps), 3.6), sharey=True, squeeze=False)
    for ax, kp in zip(axes[0], kps):
        for kd in sorted({r["kd"] for r in rows}):
            sel = sorted((r for r in rows if r["kp"] == kp and r["kd"] == kd), key=lambda r: r["omega_o"])
            w = [r["omega_o"] for r in sel]
            line, = ax.plot(w, [r["roles"] for r in sel], "o-", label=f"roles, k_d {kd:g}")
            ax.plot(w, [r["lmi"] for r in sel], "s--", color=line.get_color(), alpha=0.6, label=f"LMI, k_d {kd:g}")
        ax.set_title(f"k_p = {kp:g} 1/s²")
        ax.set_xlabel("ω_o (rad/s)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("largest certified L_N ((m/s²)/unit z)")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args) -> int:
    """Compute, print (text or ``--json``) and return 0 if the certificate holds, 1 otherwise."""
    from neso.certificate import certify_lmi, certify_literal, certify_tight

    if args.frontier:
        return _frontier(args)
    if max(len(args.kp), len(args.kd), len(args.omega_o)) > 1:
        print("neso certify: several gains are for --frontier; certify one set at a time")
        return 2
    network = None
    try:
        lipschitz = args.lipschitz
        if args.network is not None:
            lipschitz, network = _network(args)
        inputs = _inputs(args, lipschitz)
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
    if args.method in ("roles", "all"):
        results["roles"] = _roles(args, inputs, network)
    main = results[{"both": "tight", "all": "roles"}.get(args.method, args.method)]

    if args.json:
        print(json.dumps(_json(args, inputs, results, main, network), indent=2))
    else:
        if network is not None:
            print(f"network {network['path']} ({network['id']}, inputs {network['feature_set']}): exact physical L_N "
                  f"{network['certified_lipschitz_physical']:.4g} (m/s^2)/unit z, "
                  f"{network['certified_lipschitz_state']:.4g} in its state inputs "
                  f"({network['certified_lipschitz_normalised']:.4g} normalised)")
        print(f"Neural-ESO certificate: kp={inputs.kp:g} 1/s^2, kd={inputs.kd:g} 1/s, omega_o={inputs.omega_o:g} "
              f"rad/s, L_N={inputs.lipschitz:g} (m/s^2)/unit z; L1={inputs.L_1:g} m/s^3, Lu={inputs.L_u:g}, "
              f"C_f={inputs.C_f:.4g} m/s^3, lambda_c={inputs.lambda_c:.4g} ({inputs.lambda_c_rule})")
        for res in results.values():
            print("\n".join(_text(res)))
        if args.method in ("both", "all"):
            print(f"verdict ({main.method}): {'HOLDS' if main.holds else 'FAILS'}")
    return 0 if main.holds else 1
