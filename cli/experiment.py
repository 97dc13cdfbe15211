"""``neso experiment paper``: the paper's Section V in simulation, tables, JSON and plots."""
from __future__ import annotations

import json
from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("experiment", help="reproduce the paper's experiments in simulation")
    p.add_argument("name", choices=["paper", "aero", "bias"],
                   help="paper: Section V; aero: Experiment 3's near-ground aerodynamics audited (sim/README.md); "
                        "bias: what TDR learns on the measured state, on the reference, on a dithered reference "
                        "(the closed-loop bias, docs/method.md)")
    p.add_argument("--kp", type=float, default=None, help="bias: the z gain k_p flown (default the controller's)")
    p.add_argument("--kd", type=float, default=None, help="bias: the z gain k_d flown (default the controller's)")
    p.add_argument("--trials", type=int, default=5, help="trials (seeds) per method (default 5)")
    p.add_argument("--json", type=Path, help="write the results in the documented JSON shape")
    p.add_argument("--details", type=Path, help="write settling times, network certificates and timings as JSON")
    p.add_argument("--plots", type=Path, help="directory for PNG figures (paper Fig. 3, 5, 6, 7 analogues)")
    p.add_argument("--networks-out", type=Path, help="directory to save the trained networks in (safetensors)")
    p.add_argument("--omega-o", type=float, default=None, help="observer bandwidth rad/s (default 15)")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default 100, as the paper)")
    p.add_argument("--workers", type=int, default=0, help="flight processes (default: one per core)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--recipes", default=None,
                   help="comma-separated recipes flown side by side, the first reported first "
                        "(default: certified,paper; see neso/learning.py)")
    p.add_argument("--world", choices=("builtin", "px4"), default="builtin",
                   help="builtin: the simulator's own inner loop, in-process (default); px4: the networks the "
                        "built-in pipeline trains (--trials there) flown by real PX4 v1.16.0 SITL in the loop, at "
                        "wall-clock real time, one PX4 boot per flight (built by make setup). Default PX4 run: 1 trial, "
                        "15 flights per gain set (4 + 4 landings of 20 s, 6 lemniscates of 41 s, 1 TDR data flight): "
                        "7.5 min, ~9.5 min with the built-in pipeline on 2 cores; the JSON holds both worlds")
    p.add_argument("--px4-trials", type=int, default=1, help="--world px4: trials (seeds) per method in PX4 (default 1)")
    p.add_argument("--px4-gains", default="paper",
                   help="--world px4: comma-separated gain sets flown side by side: paper (kp_xy 6, kd_xy 4.5: the "
                        "faithful variant, limit-cycles ±0.2 m in xy on PX4) and px4 (kp_xy 2, kd_xy 2, for PX4's "
                        "160–200 ms attitude response); z gains are the paper's in both (default paper)")
    p.add_argument("--px4-experiments", default=None,
                   help="--world px4: comma-separated experiments (default: nominal_landing,ood_slope,"
                        "lemniscate_near_ground)")
    p.add_argument("--px4-methods", default=None, help="--world px4: only these methods (default: every method)")
    p.add_argument("--tuned", action="append", default=None, metavar="KIND=KP,KD,OMEGA_O",
                   help="fly the tuned baseline at these z gains for a kind of flight (landing, lemniscate) instead of "
                        "searching them (sim/tuning.py; both kinds needed), e.g. --tuned landing=40,12,2.5 "
                        "--tuned lemniscate=40,12,2.5")
    p.add_argument("--rotor-aero", action="store_true",
                   help="fly every flight with the literature's speed- and thrust-dependent rotor aerodynamics "
                        "(sim.rotor_aero; off in the default world)")


def run(args) -> int:
    """The experiment, with the flight budgets found before on this machine known to it (each verified before use)
    and the ones it finds kept for the next (services/certificate_cache.py)."""
    from services.certificate_cache import adopt_budgets, keep_budgets

    adopt_budgets()
    try:
        return _run(args)
    finally:
        keep_budgets()


def _run(args) -> int:
    from dataclasses import replace

    from neso.learning import RECIPES
    from sim.experiments import PaperConfig, results_json, run_paper
    from sim.report import (format_comparisons, format_labels, format_recipe_header, format_robustness, format_tables,
                            format_tuning)

    config = replace(PaperConfig(), trials=args.trials, workers=args.workers, seed=args.seed)
    if args.recipes:
        names = tuple(n.strip() for n in args.recipes.split(",") if n.strip())
        unknown = [n for n in names if n not in RECIPES]
        if unknown or not names:
            print(f"neso experiment: unknown recipe(s) {unknown}; known: {sorted(RECIPES)}")
            return 2
        config = replace(config, recipes=names)
    if args.rotor_aero:
        from sim.aero_audit import LITERATURE_ROTOR_AERO

        config = replace(config, sim_overrides=LITERATURE_ROTOR_AERO)
    if args.omega_o is not None:
        config = replace(config, omega_o_rps=args.omega_o)
    if args.epochs is not None:
        config = replace(config, epochs=args.epochs)
    if args.tuned:
        tuned = tuned_gains(args.tuned)
        if isinstance(tuned, str):
            print(f"neso experiment: {tuned}")
            return 2
        config = replace(config, tuned=tuned)
    if args.name == "aero":
        return _run_aero(config, args)
    if args.name == "bias":
        return _run_bias(config, args)
    if args.world == "px4":
        return _run_px4(config, args)
    run_ = run_paper(config)
    print()
    print(format_tuning(run_.details))
    for name, rec in run_.by_recipe.items():
        print()
        print(format_recipe_header(name, rec["details"]))
        print()
        print(format_tables(rec["results"], rec["details"]))
        print()
        print(format_comparisons(rec["results"]))
        if "robustness" in rec["results"]:
            print()
            print(format_robustness(rec["results"]))
        if "labels" in rec["details"]:
            print()
            print(format_labels(rec["details"]))
    print(f"\n{args.trials} trials per method; total {run_.seconds:.1f} s wall")
    if args.json:
        args.json.write_text(json.dumps(results_json(run_, args.trials), indent=2))
        print(f"results: {args.json}")
    if args.details:
        args.details.write_text(json.dumps(run_.details, indent=2))
    if args.networks_out:
        from sim.experiments import save_networks

        for path in save_networks(run_, args.networks_out):
            print(f"network: {path}")
    if args.plots:
        from cli.plots import write_plots

        for path in write_plots(run_, config, args.plots):
            print(f"plot: {path}")
    return 0


def tuned_gains(specs: list[str]):
    """kind → :class:`sim.tuning.ZGains` from ``KIND=KP,KD,OMEGA_O`` strings, or a one-line refusal."""
    from sim.tuning import KINDS, ZGains

    out = {}
    for spec in specs:
        kind, _, values = spec.partition("=")
        try:
            kp, kd, omega = (float(v) for v in values.split(","))
        except ValueError:
            return f"--tuned {spec!r}: give KIND=KP,KD,OMEGA_O, e.g. lemniscate=40,12,2.5"
        if kind not in KINDS or not min(kp, kd, omega) > 0:
            return f"--tuned {spec!r}: kinds are {list(KINDS)}, gains positive"
        out[kind] = ZGains(kp, kd, omega)
    if set(out) != set(KINDS):
        return f"--tuned needs every kind of flight: {list(KINDS)}"
    return out


def _run_aero(config, args) -> int:
    from sim.aero_audit import format_aero, run_aero

    result = run_aero(config)
    return _report(format_aero(result), result, args.json)


def _run_bias(config, args) -> int:
    from sim.bias_audit import config_for, format_bias, run_bias

    result = run_bias(config_for(args.kp, args.kd, config))
    return _report(format_bias(result), result, args.json)


def _report(text: str, result: dict, json_path) -> int:
    """An audit's table printed, its result written as JSON to ``json_path`` if given; exit status 0."""
    print()
    print(text)
    if json_path:
        json_path.write_text(json.dumps(result, indent=2))
        print(f"results: {json_path}")
    return 0


def _px4_config(args):
    """The PX4 world's choices from the flags, or a one-line refusal."""
    from cli.paper_px4 import PX4_EXPERIMENTS, Px4PaperConfig
    from neso.control import GAIN_SETS
    from sim.experiments import LEMNISCATE_METHODS

    split = lambda text: tuple(n.strip() for n in text.split(",") if n.strip())  # noqa: E731
    gains = split(args.px4_gains)
    experiments = split(args.px4_experiments) if args.px4_experiments else PX4_EXPERIMENTS
    methods = split(args.px4_methods) if args.px4_methods else None
    if not gains or any(g not in GAIN_SETS for g in gains):
        return f"unknown gain set(s) in {args.px4_gains!r}; known: {sorted(GAIN_SETS)}"
    if not experiments or any(e not in PX4_EXPERIMENTS for e in experiments):
        return f"unknown experiment(s) in {args.px4_experiments!r}; known: {list(PX4_EXPERIMENTS)}"
    if methods is not None and (not methods or any(m not in LEMNISCATE_METHODS for m in methods)):
        return f"unknown method(s) in {args.px4_methods!r}; known: {list(LEMNISCATE_METHODS)}"
    if args.px4_trials < 1:
        return "--px4-trials must be 1 or more"
    return Px4PaperConfig(trials=args.px4_trials, experiments=experiments, methods=methods, gains=gains)


def _run_px4(config, args) -> int:
    import time

    from cli.paper_px4 import Px4FlightError, run_px4_paper
    from sim.experiments import results_json, run_paper
    from sim.px4_sitl import missing_px4
    from sim.report import format_tuning, format_worlds

    problem = missing_px4()
    px4 = _px4_config(args)
    if problem or isinstance(px4, str):
        print(f"neso experiment: {problem or px4}")
        return 2
    started = time.perf_counter()
    print(f"built-in world: the pipeline ({args.trials} trials), whose networks the PX4 world flies")
    builtin = run_paper(config)
    print(format_tuning(builtin.details))
    print("the PX4 world flies the tuned baseline at these gains (" + (
        "given by --tuned" if config.tuned else "found by the search in the built-in world, not in PX4's") + ")")
    try:
        variants = run_px4_paper(builtin, config, px4)
    except Px4FlightError as exc:  # no free PX4 instance, or the TDR data flight could not fly: nothing to report
        print(f"neso experiment: {exc}")
        return 1
    seconds = time.perf_counter() - started
    first = next(iter(variants.values()))
    builtin_disturbance = _builtin_disturbance(builtin, config, first)
    print()
    print(format_worlds(builtin.results, variants, builtin_disturbance, builtin.details))
    print(f"\nbuilt-in world {builtin.seconds:.0f} s ({args.trials} trials); PX4 world {seconds - builtin.seconds:.0f} s "
          f"({px4.trials} trial(s), {sum(len(v['flights']) for v in variants.values())} flights); total {seconds:.0f} s")
    out = {"world": "px4", "px4_version": reported_version(variants), "experiments": first["experiments"],
           "saturation_percent": first["saturation_percent"], "trials": px4.trials, "seconds": seconds,
           "recipe": next(iter(builtin.by_recipe)), "gains": next(iter(variants)),
           "disturbance_z_std_mps2": first["disturbance_z_std_mps2"],
           "tuned_gains": {k: g.to_dict() for k, g in builtin.tuned.gains.items()},
           "tuned_gains_source": "given" if config.tuned else "searched in the built-in world",
           "variants": {g: {k: v[k] for k in ("kp", "kd", "experiments", "saturation_percent", "disturbance_z_std_mps2")}
                        for g, v in variants.items()},
           "builtin": dict(results_json(builtin, args.trials), disturbance_z_std_mps2=builtin_disturbance)}
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
        print(f"results: {args.json}")
    if args.details:
        args.details.write_text(json.dumps({"builtin": builtin.details,
                                            "px4_flights": {g: v["flights"] for g, v in variants.items()}}, indent=2))
    return 0


def reported_version(variants: dict) -> str:
    """The version PX4 itself reported in the flights (``v1.16.0 6ea3539``): one, or every one seen joined by " / "
    (a build changed under the run); "unknown" when no flight got PX4's answer."""
    seen = sorted({f.get("autopilot", "") for v in variants.values() for f in v["flights"]} - {"", "unknown"})
    return " / ".join(s.removeprefix("PX4 ") for s in seen) or "unknown"


def _builtin_disturbance(builtin, config, px4_variant: dict) -> dict:
    """The built-in world's true z disturbance spread for the experiments and methods the PX4 world flew."""
    from neso.metrics import summarise
    from sim.experiments import disturbance_z_std_mps2

    return {scenario: {m: summarise([disturbance_z_std_mps2(log, config, scenario) for log in builtin.logs[scenario][m]])
                       for m in methods} for scenario, methods in px4_variant["disturbance_z_std_mps2"].items()}
