# Real autopilots in the loop: ArduCopter SITL from SITL_DIR (../shared/sitl beside the
# checkout by default). `make test-sitl` runs tests/autopilot_sitl (the real command line
# against the simulated calibration stand); without SITL it says so and passes. `make test`
# runs it too.

.PHONY: test-sitl bench-sitl

SITL_DIR ?= ../shared/sitl

test-sitl: setup
	@if [ -x "$(SITL_DIR)/arducopter" ]; then \
		MAGCAL_SITL_DIR="$(abspath $(SITL_DIR))" $(PY) -m pytest -q tests/autopilot_sitl; \
	else \
		echo "test-sitl: skipped: no ArduPilot SITL at $(SITL_DIR)/arducopter (see tests/autopilot_sitl/ardupilot.py)"; \
	fi

TEST_EXTRA += test-sitl

# magcal beside ArduPilot's on-board calibrator on the same SITL set-ups (figures, no
# assertions): bench/sitl.json. Part of `make bench` when SITL is there.
bench-sitl: setup
	MAGCAL_SITL_DIR="$(abspath $(SITL_DIR))" $(PY) bench/sitl_bench.py --out bench/sitl.json
