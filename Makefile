# The contract: every target sets up what it needs in .venv first.
PY := .venv/bin/python
PIP := .venv/bin/pip

.PHONY: setup run test test-all lint bench reproduce clean

.venv/.installed: pyproject.toml
	python3 -m venv .venv
	$(PIP) install -q --upgrade pip
	$(PIP) install -q -e ".[dev]"
	touch $@

setup: .venv/.installed

# The default job: naive BC vs deconfounded IL on the confounded bandit, 10 seeds, CPU preset.
run: setup
	$(PY) -m jaxdeconf.run --env bandit --algo bc,dil --seeds 10 --preset cpu

test: setup
	$(PY) -m pytest -q

test-all: setup
	$(PY) -m pytest -q -m "slow or not slow"

lint: setup
	.venv/bin/ruff check src envs tests experiments examples

# Every table and figure of the paper into report/ (resumable; SCALE=paper on a GPU).
reproduce: setup
	$(PY) -m jaxdeconf.reproduce --scale $(or $(SCALE),cpu) --out report

bench: setup
	$(PY) experiments/bench.py $(SECTIONS)

clean:
	rm -rf .venv results .pytest_cache
