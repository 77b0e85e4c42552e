# Entry points (see README): `make demo`, `make demo-live`, `make demo-fleet`, `make demo-rig`
# and `make test`.
# Each sets up .venv itself. `make demo-live LAUNCH=1` starts the nodes with `ros2 launch`.
# `make docs` builds the documentation site into site/ (warnings are errors).
VENV ?= .venv
PY := $(VENV)/bin/python
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export MPLBACKEND := Agg

LAUNCH ?= 0

.PHONY: setup demo demo-live demo-fleet demo-rig demo-model ros-cli-env test test-quick lint docs clean

setup:
	@VENV=$(VENV) bash scripts/setup_env.sh

demo: setup
	@bash scripts/demo.sh $(VENV)

demo-live: setup
	@LAUNCH=$(LAUNCH) bash scripts/demo_live.sh $(VENV)

# docs/launch.md's recipe: `ros2 launch` and the ros2 CLI in a scratch folder (ROS_SOURCES=...)
ros-cli-env: setup
	@PROJECT_VENV=$(VENV) bash scripts/ros_cli_env.sh

demo-fleet: setup
	@bash scripts/demo_fleet.sh $(VENV)

# issue 49: front camera alone vs front + rear on a world with a lap driven the other way round
demo-rig: setup
	@bash scripts/demo_rig.sh $(VENV)

test: setup
	$(PY) -m pytest -q --durations=25 test

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
