# bac: the two commands are `make demo` and `make test` (see README.md).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
# every ROS process of bac stays on this machine (README.md, "The network rule")
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export AMENT_PREFIX_PATH := $(CURDIR)/$(VENV)
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp

.PHONY: setup setup-bench demo test lint unit clean

setup:
	@scripts/setup.sh

setup-bench:
	@scripts/setup.sh --bench

## make demo: set up if needed, then a whole calibration campaign on the simulated vehicle
demo: setup
	@$(PY) -m bac_bringup.cli demo $(DEMO_ARGS)

## make test: set up if needed, then lint the pure cores and run the whole test suite
## inside a private network namespace (nothing can leave this machine)
test: setup lint
	@$(PY) -m bac_bringup.netns -- $(PY) -m pytest $(PYTEST_ARGS)

lint: setup
	@$(VENV)/bin/ruff check src tests bench
	@$(VENV)/bin/ruff format --check src tests bench
	@$(VENV)/bin/mypy

clean:
	rm -rf build $(VENV)
