# One-command set-up on a fresh machine: a .venv/ in the checkout, torch first (the pinned
# CPU build, so nothing else pulls a CUDA torch), then this package with its test extra, and the
# system parts the tests and the demo need (Debian's chromium for the dashboard's browser tests).
# Quick when everything is there: the venv has a stamp, chromium is a file make checks.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
CHROMIUM := /usr/bin/chromium
DEMO_S ?= 0

.PHONY: bench-quick setup px4 demo demo-tdr test test-fast bench experiment clean

setup: $(STAMP) $(CHROMIUM) px4

# Real PX4 v1.16.0 SITL, built once into ~/.cache/neso/px4-v1.16.0 from $$PX4_SRC, ../shared/px4/ or PX4's official
# repository (a stamp makes it a no-op after; ~4 min of every core the first time). PX4's Python build requirements
# come from the package index first, into a cached venv: the build itself needs no network. No PX4 to be had: one
# line naming the three ways, and make setup fails.
px4:
	@sim/px4/build.sh requirements
	@sim/px4/build.sh

# Debian's chromium (Playwright drives it; never a downloaded browser build): as root directly,
# else through sudo, else one line saying what to run.
$(CHROMIUM):
	@if [ "$$(id -u)" = 0 ]; then sudo=""; elif command -v sudo >/dev/null 2>&1; then sudo="sudo"; \
	else echo "make setup: $(CHROMIUM) is missing; as root run: apt-get install -y --no-install-recommends chromium" >&2; exit 1; fi; \
	echo "make setup: installing Debian's chromium (apt-get) for the dashboard's browser tests"; \
	{ $$sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq --no-install-recommends chromium >/dev/null; } \
	|| { echo "make setup: could not install chromium; run: sudo apt-get install -y --no-install-recommends chromium" >&2; exit 1; }

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: setup
	$(VENV)/bin/neso experiment paper --trials 5 --plots out/plots --json out/paper.json --details out/paper-details.json
	@echo "dashboard: http://127.0.0.1:8080   (Ctrl-C stops everything; DEMO_S=60 make demo stops after 60 s)"
	$(VENV)/bin/neso up --scenario nominal_landing --mission landing_test --duration $(DEMO_S)

demo-tdr: setup
	$(VENV)/bin/neso demo tdr --workdir out/demo-tdr --json out/demo-tdr/report.json

# Every tier (unit, sim, bus, process, browser, px4; tests/README.md) on $(WORKERS) workers: on a quiet machine two
# flying lanes (PX4's flights, then NatNet's, alone beside the computing; then the others two at a time), with a core
# busy one (every flight one after another beside the computing at nice 10); NESO_TEST_LANES=1 or 2 decides instead;
# the time per tier and the slowest tests at the end.
WORKERS ?= 2
test: setup
	$(PY) -m pytest -n $(WORKERS) --durations=20

# The tiers without real-time processes or a browser, for every edit: their slow tests (each over ~30 s alone: the
# real-flight benchmark, the paper pipeline, the tuning neighbourhoods) are left to make test.
test-fast: setup
	$(PY) -m pytest -m "(unit or sim or bus) and not slow" -n 2 --durations=10

bench: setup
	$(PY) -m bench

# A subset of `make bench` in under 5 minutes (docs/benchmarks.md); the full run's sections are listed as not run.
bench-quick: setup
	$(PY) -m bench --quick

clean:
	rm -rf $(VENV) out .pytest_cache
