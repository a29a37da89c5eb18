# mshoot: one setup path, one test command, the demo, the benchmarks, the study.
SHELL := /bin/bash
ROOT := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))
RUN := source $(ROOT)/env.sh &&
PYTEST_ARGS ?=

.PHONY: setup test bench bench-setup versus clean help docs

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | sed -E 's/:.*## /\t/'

setup:  ## create .venv, install pinned wheels, build the FMUs and the ROS 2 workspace (idempotent)
	@bash $(ROOT)/tools/setup.sh

# TEST_WORKERS=2: the suite on two pytest-xdist workers (many tests wait on subprocesses and
# DDS); a file's tests stay on one worker, the tests marked host_discovery run on one worker
# one at a time (tests/conftest.py). 1 (the default): one process.
TEST_WORKERS ?= 1
XDIST_ARGS := $(if $(filter-out 0 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadgroup --no-loadscope-reorder)

test: setup  ## run every test, the docs build and its tutorials included (TEST_WORKERS=2: two workers)
	@$(RUN) cd $(ROOT) && python -m pytest $(XDIST_ARGS) $(PYTEST_ARGS)

docs: setup  ## the documentation site (Sphinx, warnings as errors) -> out/docs/html/index.html
	@$(RUN) cd $(ROOT) && python -m sphinx -W --keep-going -q -b html -d out/docs/doctrees \
		docs out/docs/html && echo "out/docs/html/index.html"

bench-setup: setup  ## install the benchmark-only packages (bench/requirements.txt: CasADi) into .venv
	@VIRTUAL_ENV=$(ROOT)/.venv $(ROOT)/.venv/bin/uv pip install -q --compile-bytecode -r $(ROOT)/bench/requirements.txt

bench: bench-setup  ## run the benchmarks (speed, tolerance, scale, versus); figures in out/bench/*.json
	@$(RUN) cd $(ROOT) && python bench/speed.py && python bench/tolerance.py && python bench/scale.py \
		&& python bench/versus.py

versus: bench-setup  ## mshoot next to CasADi/IPOPT on the same cases (~1 min) -> out/bench/versus.json
	@$(RUN) cd $(ROOT) && python bench/versus.py

clean:  ## remove build products (keeps .venv)
	rm -rf $(ROOT)/ros2_ws/build $(ROOT)/ros2_ws/install $(ROOT)/ros2_ws/log $(ROOT)/out
	rm -f $(ROOT)/.venv/.stamp-workspace

# -- the demo (mshoot_nodes): the closed loop over ROS 2 ----------------------------------------
SCENARIO ?= synthetic
OU44_CSV ?= $(abspath $(ROOT)/../shared/data/ou44/measurements.csv)
DEMO_OUT ?= out/demo
DEMO_ARGS ?=

.PHONY: demo
demo: setup  ## 72 h MPC over ROS 2 (emulator, forecaster, mpc, bag) -> out/demo/; SCENARIO=ou44 for the OU44 data
	@$(RUN) cd $(ROOT) && python -m mshoot_nodes.bringup --scenario $(SCENARIO) \
		$(if $(filter ou44,$(SCENARIO)),--data $(OU44_CSV)) --out $(DEMO_OUT) $(DEMO_ARGS)

# -- the reference study (mshoot study): every table and figure -> docs/ -----------------------
STUDY_OUT ?= docs
STUDY_ARGS ?=

.PHONY: study
study: setup  ## regenerate every table and figure of the OU44 reference study -> docs/study.md (~6 min on 2 cores)
	@$(RUN) cd $(ROOT) && mshoot study --data $(OU44_CSV) --out $(STUDY_OUT) $(STUDY_ARGS)

# -- BOPTEST's two-zone office (issue 24): the BMS and mshoot by configuration only ----------
OFFICE_DIR ?= $(dir $(ROOT))shared/boptest/multizone_office_simple_hydronic
OFFICE_CARDS := $(ROOT)/docs/boptest_cards/multizone_office_simple_hydronic
OFFICE_ARGS ?=
# the rule as `make boptest-office-tune` chose it per period and price on the full test
# periods, from the grids it wrote (docs/boptest_office/rule_tuning_<period>.csv)
OFFICE_RULE ?= --rule-grids $(ROOT)/docs/boptest_office
OFFICE_GRID ?= --leads 0 --margins 0 --cooling-margins 0 0.5 1 2 --supply-shifts -10 -20 -30

.PHONY: boptest-office
boptest-office: setup  ## the two-zone office: BMS baseline, tuned rule and mshoot, 3 periods x 2 prices, runs on 2 workers -> out/boptest_office/kpis.json, docs/boptest_office.md
	@$(RUN) cd $(ROOT) && mshoot boptest --testcase $(OFFICE_DIR) --card $(OFFICE_CARDS).yaml \
		--control-card $(OFFICE_CARDS)_control.yaml --mpc-settings $(OFFICE_CARDS)_mpc.yaml \
		--controllers baseline rule mshoot \
		--periods typical_heat_day peak_heat_day typical_cool_day \
		--prices constant highly_dynamic --uncertainty none $(OFFICE_RULE) --workers 2 \
		--out out/boptest_office --report docs/boptest_office.md $(OFFICE_ARGS)

.PHONY: boptest-office-tune
boptest-office-tune: setup  ## the two-zone office's rule tuned on the full test periods: OFFICE_GRID of full runs (~35 min on 2 cores) -> docs/boptest_office/rule_tuning_<period>.csv
	@$(RUN) cd $(ROOT) && mshoot boptest --testcase $(OFFICE_DIR) --card $(OFFICE_CARDS).yaml \
		--controllers rule --periods typical_heat_day peak_heat_day typical_cool_day \
		--prices constant highly_dynamic $(OFFICE_GRID) --workers 2 \
		--out out/boptest_office_tune && mkdir -p docs/boptest_office && \
		cp out/boptest_office_tune/rule_tuning_*.csv docs/boptest_office/

# -- the soak benchmark (issue 6): many simulated days over ROS 2 with faults injected ---------
SOAK_DAYS ?= 30
SOAK_SEED ?= 1
SOAK_ARGS ?=

.PHONY: soak
soak: setup  ## soak: SOAK_DAYS (30) simulated days over ROS 2 with seeded random faults -> out/soak/
	@$(RUN) cd $(ROOT) && python bench/soak.py --days $(SOAK_DAYS) --seed $(SOAK_SEED) \
		--out out/soak $(SOAK_ARGS)

# -- BOPTEST (issue 15): baseline, tuned rule and mshoot on bestest_hydronic_heat_pump ---------
BOPTEST_OUT ?= out/boptest
BOPTEST_ARGS ?=

.PHONY: boptest
boptest: setup  ## BOPTEST: baseline, rule (tuned) and mshoot over ROS 2, 2 periods x 3 prices -> out/boptest/kpis.json, docs/boptest.md
	@$(RUN) cd $(ROOT) && python -m mshoot_nodes.boptest_run \
		--card docs/boptest_cards/bestest_hydronic_heat_pump.yaml --starts-output reaHeaPumY_y \
		--out $(BOPTEST_OUT) --docs docs $(BOPTEST_ARGS)
