# mshoot: one setup path, one test command, the demo, the benchmarks, the study.
SHELL := /bin/bash
ROOT := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))
RUN := source $(ROOT)/env.sh &&
PYTEST_ARGS ?=

.PHONY: setup test test-all bench clean help

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | sed -E 's/:.*## /\t/'

setup:  ## create .venv, install pinned wheels, build the FMUs and the ROS 2 workspace (idempotent)
	@bash $(ROOT)/tools/setup.sh

test: setup  ## run the whole default test suite (slow tests excluded)
	@$(RUN) cd $(ROOT) && python -m pytest $(PYTEST_ARGS)

test-all: setup  ## run every test, slow ones included
	@$(RUN) cd $(ROOT) && python -m pytest -m '' $(PYTEST_ARGS)

bench: setup  ## run the benchmarks (speed, tolerance, scale); figures in out/bench/*.json
	@$(RUN) cd $(ROOT) && python bench/speed.py && python bench/tolerance.py && python bench/scale.py

clean:  ## remove build products (keeps .venv)
	rm -rf $(ROOT)/ros2_ws/build $(ROOT)/ros2_ws/install $(ROOT)/ros2_ws/log $(ROOT)/out
	rm -f $(ROOT)/.venv/.stamp-workspace
