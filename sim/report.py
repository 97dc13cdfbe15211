"""Text tables shaped like the paper's (mean ± std over trials, cm), from the results dict."""
from __future__ import annotations

from neso.certificate import POLICY
from sim.tuning import SCENARIO_KIND, TUNED, TUNED_GAINS

PAPER_FIGURES_CM = {
    "nominal_landing": {"pd": 10.95, "pd_nn": 2.49, "pd_eso": 1.84, "neural_eso": 0.37},
    "ood_slope": {"pd_nn": 3.74, "pd_eso": 0.66, "neural_eso": 1.53},
    "lemniscate_near_ground": {"pd": 4.08, "pd_nn": 5.47, "pd_eso": 1.91, "neural_eso": 4.09, "neural_eso_tdr": 0.89},
    "lipschitz_ablation": {
        "nominal": {"0.2": 2.73, "0.5": 0.71, "1.0": 0.37, "2.0": 1.43},
        "ood": {"0.2": 1.69, "0.5": 0.63, "1.0": 1.53, "2.0": 2.59},
    },
}


def _cell(result: dict) -> str:
    if result["mean"] is None:
        return f"diverged {result['diverged']}/{len(result['trials'])}"
    text = f"{result['mean']:.2f} ± {result['std']:.2f}"
    if result["diverged"]:
        text += f" ({result['diverged']} div.)"
    return text


def _table(title: str, rows: list[tuple[str, ...]]) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [title]
    for i, row in enumerate(rows):
        lines.append("  " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths)))
        if i == 0:
            lines.append("  " + "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_recipe_header(name: str, details: dict) -> str:
    """One line per recipe: which inputs, which bound, whether its networks are certified."""
    nets = details.get("networks", {})
    base = nets.get("base_x1", {})
    tdr = nets.get("tdr", {})
    tuned = nets.get("tdr_tuned", {})
    cert = lambda n: ("certified" if n.get("certificate_holds") else "NOT certified") if n else "–"  # noqa: E731
    def learned(n: dict) -> str:
        vs = n.get("val_loss_vs_mean")
        gain = n.get("gain_change")
        return ((f", val loss {vs:.3f} × the mean's" if isinstance(vs, float) else "") +
                (f", as gain Δk_p {gain['dkp']:+.2f}, Δk_d {gain['dkd']:+.2f}" if gain else ""))

    return (f"=== recipe {name}: inputs {details.get('feature_set')}, bound {details.get('base_bound', float('nan')):.4g} "
            f"({details.get('bound_units')}); base network {cert(base)} (L_N in its state inputs "
            f"{base.get('certified_lipschitz_state', float('nan')):.3g}, all inputs "
            f"{base.get('certified_lipschitz_physical', float('nan')):.3g}, vs largest certified "
            f"{base.get('largest_certified_physical', float('nan')):.3g}{learned(base)}), TDR network {cert(tdr)} "
            f"({tdr.get('certified_lipschitz_state', float('nan')):.3g}{learned(tdr)})" +
            (f"; at the tuned gains TDR network {cert(tuned)} ({tuned.get('certified_lipschitz_state', float('nan')):.3g}"
             f"{learned(tuned)})" if tuned else "") + " ===")


def format_labels(details: dict) -> str:
    """The labels against the simulator's truth (sim.experiments.label_quality)."""
    rows = [("flight · label", "RMS vs truth [m/s²]", "best-match shift [ms] · corr(error, Ṫ_cmd)")]
    for flight, by_kind in details.get("labels", {}).items():
        for kind, q in by_kind.items():
            rows.append((f"{flight} · {kind}", f"{q['rms_mps2']:.3f}",
                         f"{q['lag_s'] * 1e3:.0f} · {q['corr_with_thrust_rate']:+.2f}"))
    return _table("Labels against the simulator's truth (disturbance relative to the applied thrust)", rows)


def format_tables(results: dict, details: dict | None = None) -> str:
    out = []
    for name, title in (
        ("nominal_landing", "Experiment 1 — nominal landing: steady-state |z error| [cm]"),
        ("ood_slope", "Experiment 2 — OOD slope: steady-state |z error| [cm]"),
        ("lemniscate_near_ground", "Experiment 3 — lemniscate near ground: z RMSE [cm]"),
    ):
        if name not in results:
            continue
        rows = [("method", "sim (mean ± std)", "paper (hardware)")]
        settle = (details or {}).get("settling_time_s", {}).get(name, {})
        for method, result in results[name]["methods"].items():
            cell = _cell(result)
            if method in settle and settle[method]["mean"] is not None:
                cell += f"   settles {settle[method]['mean']:.2f} s"
            paper = PAPER_FIGURES_CM[name].get(method)
            rows.append((_method_label(method, name, details), cell, "—" if paper is None else f"{paper:.2f}"))
        out.append(_table(title, rows))
    if "noise_free_nominal" in results:
        nf = results["noise_free_nominal"]
        rows = [("method", "steady-state |e_z| [cm]", "thrust std [N]  ·  error peak [Hz]")]
        for method, result in nf["methods"].items():
            std, peak = nf["thrust_std_n"][method], nf["peak_hz"][method]
            rows.append((_method_label(method, "nominal_landing_noiseless", details), _cell(result),
                         f"{_num(std)}  ·  {_num(peak)}"))
        out.append(_table("Noise-free nominal landing (motion capture without noise)", rows))
    if "lipschitz_ablation" in results:
        rows = [(f"L_N ({results['lipschitz_ablation'].get('units', 'normalised')})", "nominal", "OOD")]
        abl = results["lipschitz_ablation"]
        paper_keys = list(PAPER_FIGURES_CM["lipschitz_ablation"]["nominal"])  # the same factors of the base bound
        for i, bound in enumerate(abl["nominal"]):
            key = paper_keys[i] if i < len(paper_keys) else bound
            paper_n = PAPER_FIGURES_CM["lipschitz_ablation"]["nominal"].get(key)
            paper_o = PAPER_FIGURES_CM["lipschitz_ablation"]["ood"].get(key)
            rows.append((
                bound,
                f"{_cell(abl['nominal'][bound])}  (paper {paper_n})",
                f"{_cell(abl['ood'][bound])}  (paper {paper_o})",
            ))
        out.append(_table("L_N ablation — Neural-ESO steady-state |z error| [cm]", rows))
    return "\n\n".join(out)


def _method_label(method: str, scenario: str, details: dict | None) -> str:
    """``method``, and for one flown at other gains than the paper's the gains (``details["tuned_gains"]``, and
    ``details["tdr_as_gain"]`` for PD+ESO flown at a TDR network's slopes added to the gains)."""
    gains = (details or {}).get("tdr_as_gain", {}).get(method) or (
        (details or {}).get("tuned_gains", {}).get(SCENARIO_KIND.get(scenario, "")) if method.endswith(TUNED) else None)
    if not gains:
        return method
    return f"{method} (k_p {gains['kp']:.3g}, k_d {gains['kd']:.3g}, ω_o {gains['omega_o']:g})"


def format_tuning(details: dict) -> str:
    """The tuned baseline's gains per kind of flight and how they were found (sim.tuning)."""
    t = details.get("tuning") or {}
    if t.get("given"):
        gains = details.get("tuned_gains", {})
        return "Tuned PD+ESO: gains given, not searched: " + "; ".join(
            f"{k} k_p {g['kp']:g}, k_d {g['kd']:g}, ω_o {g['omega_o']:g}" for k, g in gains.items())
    if not t:
        return "Tuned PD+ESO: no search recorded"
    c = t["config"]
    lines = [f"Tuned PD+ESO (sim.tuning): grid k_p {c['kp_grid']} × k_d {c['kd_grid']} × ω_o {c['omega_o_grid']} on "
             f"tuning seeds {t['seeds']} (not the evaluation seeds); conditions: no crash, at ×{c['noise_factor']:g} "
             f"noise every hold at 0.1 m flown and its thrust std ≤ ×{c['max_thrust_std_ratio']:g} the paper gains' "
             f"({t['paper_robustness']['thrust_std_n']:.2f} N), noise-free thrust std ≤ ×{c['max_thrust_std_ratio']:g} "
             f"theirs ({t['paper_robustness']['quiet_thrust_std_n']:.3f} N), PD+ESO certified with an |e_z| bound "
             f"≤ ×{POLICY.max_bound_ratio:g} the paper gains' ({t['paper_certificate']['pdeso_bound_cm']:.3g} cm) "
             f"and a learned budget ≥ ×{c['min_budget_fraction']:g} theirs "
             f"({t['paper_certificate']['budget']:.3g} (m/s²)/unit z)"]
    for kind, k in t["kinds"].items():
        g, rob, cert = k["gains"], k["robustness"], k["certificate"]
        paper = k.get("paper_objective_cm")
        first = "; ".join(f"({r['kp']:g}, {r['kd']:g}, {r['omega_o']:g}): {r['why'][0]}" for r in k["rejected"][:3])
        lines.append(
            f"  {kind}: k_p {g['kp']:g}, k_d {g['kd']:g}, ω_o {g['omega_o']:g}: {_opt(k['objective_cm'])} cm on the "
            f"tuning seeds (paper gains {_opt(paper)}); ×{c['noise_factor']:g} noise: thrust std "
            f"{_opt(rob['thrust_std_n'])} N, hold z RMS {_opt(rob['z_rms_cm'])} cm; noise-free thrust std "
            f"{_opt(rob['quiet_thrust_std_n'], '.3f')} N; budget {_opt(cert.get('budget'), '.3g')}, PD+ESO bound "
            f"{_opt(cert.get('pdeso_bound_cm'), '.3g')} cm" + (" — NONE MET THE CONDITIONS" if k.get("none_met") else "")
            + (f"; {len(k['rejected'])} better point(s) failed: {first}" if k["rejected"] else ""))
        stated = TUNED_GAINS.get(kind)
        if stated is not None and stated.to_dict() != g:
            lines.append(f"    (not sim.tuning.TUNED_GAINS[{kind!r}], {stated.text()}, which neso demo tdr flies: the "
                         "world or the search changed since it was stated)")
    return "\n".join(lines)


def _opt(v, form: str = ".2f") -> str:
    return "–" if v is None else format(v, form)


def format_robustness(results: dict) -> str:
    """The tuning's conditions measured on the evaluation seeds for PD+ESO and the learned pathway at both gains."""
    rb = results.get("robustness")
    if not rb:
        return ""
    out = []
    for kind, by_method in rb["kinds"].items():
        rows = [("method", f"×{rb['noise_factor']:g} noise: holds flown",
                 "hold thrust std [N] · z RMS [cm] · peak [Hz]", "lemniscate flown · RMSE [cm] (reported)",
                 "noise-free thrust std [N]", "meets the conditions")]
        for m, r in by_method.items():
            lem = (f"{r['lemniscate_flown']}/{r['lemniscate_total']} · {_opt(r['lemniscate_rmse_cm'])}"
                   if r["lemniscate_total"] else "–")
            rows.append((m, f"{r['hold_flown']}/{r['hold_total']}",
                         f"{_opt(r['thrust_std_n'])} · {_opt(r['z_rms_cm'])} · {_opt(r['peak_hz'])}", lem,
                         _opt(r["quiet_thrust_std_n"], ".3f"),
                         "yes" if not r.get("why") else "NO: " + "; ".join(r["why"])))
        out.append(_table(f"Robustness, {kind} gains (evaluation seeds; the conditions of the tuning, against pd_eso)",
                          rows))
    return "\n\n".join(out)


def comparisons(results: dict) -> list[tuple[str, bool, str]]:
    """The paper's claims checked on these results: (claim, holds, figures)."""
    def mean(exp, method):
        return results[exp]["methods"][method]["mean"]

    claims = []
    nl = "nominal_landing"
    if nl in results:
        order = ["neural_eso", "pd_eso", "pd_nn", "pd"]
        means = [mean(nl, m) for m in order]
        holds = None not in means and all(a < b for a, b in zip(means, means[1:]))
        ratio = means[0] / means[1] if None not in means[:2] else None
        claims.append(("nominal: neural_eso < pd_eso < pd_nn < pd", bool(holds),
                       " < ".join(f"{m} {v}" for m, v in zip(order, _fmt(means))) +
                       (f"; neural_eso/pd_eso = {ratio:.2f} (paper 0.20)" if ratio is not None else "")))
    if "ood_slope" in results:
        a, b = mean("ood_slope", "neural_eso"), mean("ood_slope", "pd_nn")
        div = results["ood_slope"]["methods"]["neural_eso"]["diverged"]
        claims.append(("OOD slope: neural_eso bounded and better than pd_nn",
                       a is not None and div == 0 and (b is None or a < b), f"neural_eso {_fmt([a])[0]}, pd_nn {_fmt([b])[0]}"))
    le = "lemniscate_near_ground"
    if le in results:
        tdr, eso = mean(le, "neural_eso_tdr"), mean(le, "pd_eso")
        gain = None if None in (tdr, eso) else 1 - tdr / eso
        claims.append(("lemniscate: neural_eso_tdr beats pd_eso by ≥ 45 %", gain is not None and gain >= 0.45,
                       f"reduction {gain * 100:.1f} % (paper 53.4 %)" if gain is not None else "n/a"))
        methods = results[le]["methods"]
        nobs = methods["neural_observer"]
        worst = max((r["mean"] for m, r in methods.items() if r["mean"] is not None and m != "neural_observer"), default=0)
        claims.append(("lemniscate: neural_observer diverges or is worst",
                       nobs["diverged"] > 0 or (nobs["mean"] is not None and nobs["mean"] >= worst),
                       f"neural_observer {_cell(nobs)}, worst other {worst:.2f}"))
        claims.append(("lemniscate: pd_nn worse than pd_eso", (mean(le, "pd_nn") or float("inf")) > (eso or 0),
                       f"pd_nn {_fmt([mean(le, 'pd_nn')])[0]}, pd_eso {_fmt([eso])[0]}"))
    return claims + tuned_comparisons(results)


def tuned_comparisons(results: dict) -> list[tuple[str, bool, str]]:
    """Against PD+ESO at the tuned gains, the baseline a learned pathway is said to pay against (issue 32)."""
    def mean(exp, method):
        return results.get(exp, {}).get("methods", {}).get(method, {}).get("mean")

    def ratio(a, b):
        return None if a is None or b is None or b <= 0 else a / b

    claims = []
    for exp in ("nominal_landing", "ood_slope", "lemniscate_near_ground"):
        r = ratio(mean(exp, "pd_eso_tuned"), mean(exp, "pd_eso"))
        if r is not None:
            claims.append((f"{exp}: tuned PD+ESO no worse than at the paper's gains", r <= 1.0,
                           f"pd_eso_tuned / pd_eso = {r:.2f}"))
    r = ratio(mean("nominal_landing", "neural_eso_tuned"), mean("nominal_landing", "pd_eso_tuned"))
    if r is not None:
        rp = ratio(mean("nominal_landing", "neural_eso"), mean("nominal_landing", "pd_eso_tuned"))
        claims.append(("nominal: neural_eso ≤ 0.8 × tuned PD+ESO, both at the tuned gains", r <= 0.8,
                       f"neural_eso_tuned / pd_eso_tuned = {r:.2f}" +
                       (f" (neural_eso at the paper's gains / pd_eso_tuned = {rp:.2f})" if rp is not None else "")))
    le = "lemniscate_near_ground"
    r = ratio(mean(le, "neural_eso_tdr_tuned"), mean(le, "pd_eso_tuned"))
    if r is not None:
        rp = ratio(mean(le, "neural_eso_tdr"), mean(le, "pd_eso_tuned"))
        claims.append(("lemniscate: TDR ≥ 10 % below tuned PD+ESO, both at the tuned gains", r <= 0.9,
                       f"neural_eso_tdr_tuned vs pd_eso_tuned {(r - 1) * 100:+.1f} %" +
                       (f" (TDR at the paper's gains vs pd_eso_tuned: {(rp - 1) * 100:+.1f} %)" if rp is not None
                        else "")))
    for suffix, where in (("", "the paper's gains"), (TUNED, "the tuned gains")):
        tdr, gain, eso = (mean(le, f"{m}{suffix}") for m in ("neural_eso_tdr", "pd_eso_tdr_gain", "pd_eso"))
        if None not in (tdr, gain, eso):
            claims.append((f"lemniscate at {where}: TDR beats its own slopes flown as gain by PD+ESO", tdr < gain,
                           f"vs pd_eso{suffix}: TDR {(tdr / eso - 1) * 100:+.1f} %, its slopes as gain alone "
                           f"{(gain / eso - 1) * 100:+.1f} %"))
    return claims


def _num(result: dict) -> str:
    return "–" if result.get("mean") is None else f"{result['mean']:.3f} ± {result['std']:.3f}"


def _fmt(values):
    return ["div." if v is None else f"{v:.2f}" for v in values]


def format_comparisons(results: dict) -> str:
    lines = ["The paper's comparisons in this simulation:"]
    for claim, holds, figures in comparisons(results):
        lines.append(f"  [{'holds' if holds else 'FAILS'}] {claim}: {figures}")
    return "\n".join(lines)


def format_worlds(builtin: dict, variants: dict, builtin_disturbance: dict, details: dict | None = None) -> str:
    """The experiments flown in both worlds side by side with the paper's figures (cm, mean ± std):
    ``builtin`` the built-in world's ``experiments``, ``variants`` gain set → the PX4 world's
    (``neso experiment paper --world px4``), with the PX4 allocator's saturation (% of airborne sensor periods)
    and the true z disturbance's spread (std, m/s²) in each world (``builtin_disturbance`` the built-in's);
    ``details``: the built-in run's, whose tuned gains label the ``_tuned`` methods."""
    names = list(variants)
    head = ("method", "paper", "built-in world", *(f"PX4, gains {g}" for g in names),
            *(f"PX4 sat. % ({g})" for g in names), "f_z std built-in", *(f"f_z std PX4 ({g})" for g in names))
    out = []
    for scenario in next(iter(variants.values()))["experiments"]:
        rows = [head]
        for method in variants[names[0]]["experiments"][scenario]["methods"]:
            paper = PAPER_FIGURES_CM.get(scenario, {}).get(method)
            ours = builtin.get(scenario, {}).get("methods", {}).get(method)
            rows.append((_method_label(method, scenario, details), "–" if paper is None else f"{paper:.2f}",
                         _cell(ours) if ours else "–",
                         *(_cell(variants[g]["experiments"][scenario]["methods"][method]) for g in names),
                         *(_sat(variants[g]["saturation_percent"][scenario][method]) for g in names),
                         _sat(builtin_disturbance[scenario][method], "{:.2f}"),
                         *(_sat(variants[g]["disturbance_z_std_mps2"][scenario][method], "{:.2f}") for g in names)))
        out.append(_table(f"{scenario} ({variants[names[0]]['experiments'][scenario]['metric']})", rows))
    return "\n\n".join(out)


def _sat(result: dict, form: str = "{:.1f}") -> str:
    return "–" if result["mean"] is None else form.format(result["mean"])
