# Entry points (see README): `make demo`, `make demo-fleet` and `make test`. Each sets up .venv
# itself. `make docs` builds the documentation site into site/ (warnings are errors).
VENV ?= .venv
PY := $(VENV)/bin/python
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export MPLBACKEND := Agg

.PHONY: setup demo demo-fleet demo-model test test-quick lint docs clean

setup:
	@VENV=$(VENV) bash scripts/setup_env.sh

demo: setup
	@bash scripts/demo.sh $(VENV)

demo-fleet: setup
	@bash scripts/demo_fleet.sh $(VENV)

test: setup
	$(PY) -m pytest -q test

test-quick: setup
	$(PY) -m pytest -q -m "not slow" test

docs: setup
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf build install log demo_out site .pytest_cache

demo-model: setup
	@PY=$(PY) bash scripts/train_demo_model.sh
