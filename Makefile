# SPDX-License-Identifier: Apache-2.0
# magcal: the one entry point. `make demo` and `make test` set everything up themselves.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT := out

.PHONY: setup demo test test-native lint accuracy real cramer-rao bench clean firmware-lib

# The portable library is every file in firmware/src; ports (POSIX SIL device, Cortex-M4
# target) live in firmware/port/ and are built by their own targets.
FW_SRC := $(wildcard firmware/src/*.c)
FW_HDR := $(wildcard firmware/include/magcal/*.h)
FW_WARN := -std=c99 -Wall -Wextra -Wpedantic -Werror
FW_INC := -Ifirmware/include

# Each part of the build that grew its own rules has a fragment in mk/ (cross-building and
# QEMU, protocol generation and fuzzing, the product installed on its own). A fragment adds
# what `make test` must also run to TEST_EXTRA.
TEST_EXTRA :=
# The pytest suites run in PYTEST_WORKERS processes (pytest-xdist; 0: in make's own), one per
# core of CI's machine: the suite is mostly computation, and two processes run it in about
# half the time one takes (1,196 s of tests in 638 s). Each module's tests go to one process
# (--dist loadscope), so a module's fixtures (a calibrated session, a study, Chromium) are
# made once.
PYTEST_WORKERS ?= 2
.DEFAULT_GOAL := setup
include $(sort $(wildcard mk/*.mk))

setup: $(STAMP)

# Re-install when a package definition, the lock (mk/deps.mk) or the native kernel changes
# (the editable install compiles host/csrc into magcal/calib/likelihood/_mekf*.so). The
# evaluation (evaluation/: accuracy checks, Cramér–Rao bound, magcal study, the demo) goes in
# after the product it imports.
$(STAMP): host/pyproject.toml host/setup.py evaluation/pyproject.toml host/requirements.lock $(wildcard host/csrc/*.c host/csrc/*.h)
	@$(PYTHON) -c "import sysconfig,os,sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()['include'],'Python.h')))" \
		|| { echo "make setup: $(PYTHON) has no C headers (Python.h), needed to build the native kernel: install python3-dev (Debian/Ubuntu) or python3-devel (Fedora)" >&2; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	PIP_CONSTRAINT=$(CURDIR)/$(LOCK) $(PY) -m pip install --quiet --upgrade pip
	PIP_CONSTRAINT=$(CURDIR)/$(LOCK) $(PY) -m pip install --quiet -e 'host[dev]'
	PIP_CONSTRAINT=$(CURDIR)/$(LOCK) $(PY) -m pip install --quiet -e evaluation
	# Editable installs leave the sources uncompiled, and where PYTHONDONTWRITEBYTECODE is set
	# nothing caches them: every cold command would compile magcal's modules again (~0.1 s
	# of each `magcal calibrate`). Compiled once here; Python checks each against its source.
	$(PY) -m compileall -q host/src evaluation/src
	touch $@

# The end-to-end demo (magcal_evaluation.demo): the SIL device with a random distortion, tumbled by the
# world simulator while collect, calibrate, flash and verify run; before/after against the truth.
# DEMO_ARGS, e.g. "--seed 3 --speedup 1", are passed on.
demo: setup sil
	$(PY) -m magcal_evaluation.demo --no-build --out $(OUT)/demo $(DEMO_ARGS)

lint: setup
	$(VENV)/bin/ruff check host evaluation tests bench
	$(VENV)/bin/ruff format --check host evaluation tests bench

test: setup deps-target lint test-native firmware-lib $(TEST_EXTRA)
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadscope tests --ignore=tests/target --ignore=tests/autopilot_sitl

# ---------------------------------------------------------------- firmware (native)
# Native tests (no Python) under AddressSanitizer and UndefinedBehaviorSanitizer: the EKF
# kernel's, and one program per tests/native/test_fw_*.c linked with the firmware library.
NATIVE_CFLAGS := $(FW_WARN) -O1 -g -ffp-contract=off \
	-fsanitize=address,undefined -fno-sanitize-recover=all
FW_TESTS := $(patsubst tests/native/%.c,build/native/%,$(wildcard tests/native/test_fw_*.c))
test-native: build/native/test_mekf_sanitizers $(FW_TESTS)
	@set -e; for t in $^; do echo "== $$t"; $$t; done

build/native/test_mekf_sanitizers: tests/native/test_mekf_sanitizers.c host/csrc/mekf_likelihood.c host/csrc/mekf_fisher.c host/csrc/mekf_likelihood.h host/csrc/mekf_step.h
	@mkdir -p $(@D)
	gcc $(NATIVE_CFLAGS) -Ihost/csrc tests/native/test_mekf_sanitizers.c \
		host/csrc/mekf_likelihood.c host/csrc/mekf_fisher.c -lm -o $@

# Tests of the POSIX port #include its .c files, so those are prerequisites too.
build/native/test_fw_%: tests/native/test_fw_%.c tests/native/check.h $(wildcard tests/native/*.h) \
		$(FW_SRC) $(FW_HDR) $(wildcard firmware/port/posix/*.[ch])
	@mkdir -p $(@D)
	gcc $(NATIVE_CFLAGS) $(FW_INC) -Itests/native $< $(FW_SRC) -lm -o $@

# The library as a shared object, for the pytest tests that drive it through ctypes.
firmware-lib: build/libmagcal_fw.so
build/libmagcal_fw.so: $(FW_SRC) $(FW_HDR)
	@mkdir -p $(@D)
	gcc $(FW_WARN) -O2 -fPIC -shared $(FW_INC) $(FW_SRC) -o $@

# The accuracy checks (bench/accuracy.md) and the paper's Figure 8 from their Table 2 runs
# (bench/figure8.png, which README.md shows); the raw per-run figures go to $(OUT)/accuracy.
accuracy: setup
	$(PY) -m magcal_evaluation.accuracy_report --runs 20 --table2-runs 150 --out bench/accuracy.md --plots $(OUT)/accuracy --figure8 bench/figure8.png

# Every method on real recordings with an optical reference attitude, against the plain
# ellipsoid fit and the known-attitude floor (REALDATA: the data set, shared/realdata beside
# the checkout by default). Exits 1 when an acceptance criterion fails, after writing.
REALDATA ?= ../shared/realdata
real: setup
	$(PY) -m magcal_evaluation.real_report --data $(REALDATA) --out bench/real.md --raw $(OUT)/real.json

# The Cramér–Rao bound of the MEMS checks with unknown translational accelerations.
cramer-rao: setup
	$(PY) -m magcal_evaluation.cramer_rao_report --runs 20 --out bench/cramer_rao.md

bench: setup sil
	$(PY) bench/run_bench.py --out bench/results.json
	$(PY) bench/firmware_figures.py --out bench/firmware.json
	$(PY) bench/link_figures.py --out bench/link.json
	$(MAKE) bench-sitl

clean:
	rm -rf $(OUT) build host/build host/src/*.egg-info evaluation/build evaluation/src/*.egg-info $(STAMP)
	find host -name '_mekf*.so' -delete
