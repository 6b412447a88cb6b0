# SPDX-License-Identifier: Apache-2.0
# Real autopilots in the loop: ArduCopter SITL from SITL_DIR (../shared/sitl beside the
# checkout by default) and PX4 SITL with SIH from PX4SITL_DIR (../shared/px4sitl). `make
# test-sitl` runs tests/autopilot_sitl (the real command line against the simulated vehicles);
# an autopilot whose SITL is absent is skipped with a message. `make test` runs it too.
# The simulators mostly wait for the clock, so the two files run side by side in
# PYTEST_WORKERS processes (the Makefile), one file to a process (--dist loadfile): ArduPilot's
# cases one after another (their SITL instances are picked one at a time), and PX4's tests on
# the one vehicle of their module. 307 s of tests ran in 200 s so beside a busy machine.

.PHONY: test-sitl bench-sitl

SITL_DIR ?= ../shared/sitl
PX4SITL_DIR ?= ../shared/px4sitl

test-sitl: setup
	@if [ ! -x "$(SITL_DIR)/arducopter" ]; then \
		echo "test-sitl: skipped: no ArduPilot SITL at $(SITL_DIR)/arducopter (see tests/autopilot_sitl/ardupilot.py)"; \
	fi
	@if [ ! -f "$(PX4SITL_DIR)/px4-sih.tar.gz" ]; then \
		echo "test-sitl: skipped: no PX4 SITL at $(PX4SITL_DIR)/px4-sih.tar.gz (see tests/autopilot_sitl/px4.py)"; \
	fi
	@if [ -x "$(SITL_DIR)/arducopter" ] || [ -f "$(PX4SITL_DIR)/px4-sih.tar.gz" ]; then \
		MAGCAL_SITL_DIR="$(abspath $(SITL_DIR))" MAGCAL_PX4SITL_DIR="$(abspath $(PX4SITL_DIR))" \
			$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile tests/autopilot_sitl; \
	fi

TEST_EXTRA += test-sitl

# magcal beside ArduPilot's on-board calibrator on the same SITL set-ups (figures, no
# assertions): bench/sitl.json. Part of `make bench` when SITL is there.
bench-sitl: setup
	MAGCAL_SITL_DIR="$(abspath $(SITL_DIR))" $(PY) bench/sitl_bench.py --out bench/sitl.json
