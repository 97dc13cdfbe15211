# One-command set-up on a fresh machine: a .venv/ in the checkout, torch first (the pinned
# CPU build, so nothing else pulls a CUDA torch), then this package with its test extra.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_S ?= 0

.PHONY: setup demo demo-tdr test bench experiment clean

setup: $(STAMP)

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

test: setup
	$(PY) -m pytest

bench: setup
	$(PY) -m bench

clean:
	rm -rf $(VENV) out .pytest_cache
