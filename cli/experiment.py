"""``neso experiment paper``: the paper's Section V in simulation, tables, JSON and plots."""
from __future__ import annotations

import json
from pathlib import Path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("experiment", help="reproduce the paper's experiments in simulation")
    p.add_argument("name", choices=["paper", "aero"],
                   help="paper: Section V; aero: Experiment 3's near-ground aerodynamics audited (sim/README.md)")
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
    p.add_argument("--rotor-aero", action="store_true",
                   help="fly every flight with the literature's speed- and thrust-dependent rotor aerodynamics "
                        "(sim.rotor_aero; off in the default world)")


def run(args) -> int:
    from dataclasses import replace

    from neso.learning import RECIPES
    from sim.experiments import PaperConfig, results_json, run_paper
    from sim.report import format_comparisons, format_labels, format_recipe_header, format_tables

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
    if args.name == "aero":
        return _run_aero(config, args)
    run_ = run_paper(config)
    for name, rec in run_.by_recipe.items():
        print()
        print(format_recipe_header(name, rec["details"]))
        print()
        print(format_tables(rec["results"], rec["details"]))
        print()
        print(format_comparisons(rec["results"]))
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


def _run_aero(config, args) -> int:
    from sim.aero_audit import format_aero, run_aero

    result = run_aero(config)
    print()
    print(format_aero(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
        print(f"results: {args.json}")
    return 0
