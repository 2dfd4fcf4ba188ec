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
## inside a private network namespace (nothing can leave this machine), on TEST_WORKERS
## pytest-xdist workers (default 2; 0: one process), each in a namespace of its own
## (scripts/test-worker), whole files to a worker (a module's campaign runs once). pytest-rerunfailures
## (colcon-core's, unused here) would have each worker dial the main process on 127.0.0.1, another namespace.
## A crashed worker ends the run (--max-worker-restart=0): xdist would hand its file to a new worker again and
## again, and a new worker (gw2) would share a live one's ROS domains. Use TEST_WORKERS, not -n (plain workers
## would share one namespace).
TEST_WORKERS ?= 2
XDIST_ARGS := $(if $(filter-out 0,$(TEST_WORKERS)),--tx $(TEST_WORKERS)*popen//python=$(CURDIR)/scripts/test-worker --dist loadfile --no-loadscope-reorder --max-worker-restart=0 -p no:rerunfailures,-p no:xdist)
test: setup lint
	@[[ "$(TEST_WORKERS)" =~ ^(0|[1-9][0-9]*)$$ ]] || { echo "TEST_WORKERS must be a number of workers (0: one process), not '$(TEST_WORKERS)'" >&2; exit 2; }
	@$(PY) -m bac_bringup.netns -- $(PY) -m pytest $(XDIST_ARGS) $(PYTEST_ARGS)

lint: setup
	@$(VENV)/bin/ruff check src tests bench
	@$(VENV)/bin/ruff format --check src tests bench
	@$(VENV)/bin/mypy

clean:
	rm -rf build $(VENV)
