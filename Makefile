# Set-up is part of every target: a fresh machine needs only python3 (>= 3.11) and make.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The test tiers on every core (pytest-xdist), each test file whole on one worker: a module's
# fixtures are built once, and the files share no state.
PARALLEL := -n auto --dist loadfile

.PHONY: run test test-all bench clean

$(STAMP): pyproject.toml constraints.txt
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test,ray]"
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/swarmpc run swap-2d --overwrite

test: $(STAMP)
	if [ -f scripts/install-browser.sh ]; then bash scripts/install-browser.sh; fi
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	$(PY) -m pytest $(PARALLEL)
	$(PY) -m pytest $(PARALLEL) -m 'loop and not slow'

test-all: $(STAMP)
	$(PY) -m pytest -m ""

bench: $(STAMP)
	$(PY) benchmarks/admm_vs_centralized.py

clean:
	rm -rf $(VENV) results
