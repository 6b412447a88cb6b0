# magcal: the one entry point. `make demo` and `make test` set everything up themselves.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT := out

.PHONY: setup demo test test-native lint accuracy bench clean

setup: $(STAMP)

# Re-install when the package definition or the native kernel changes (the editable
# install compiles host/csrc into magcal/calib/_mekf*.so).
$(STAMP): host/pyproject.toml host/setup.py $(wildcard host/csrc/*.c host/csrc/*.h)
	@$(PYTHON) -c "import sysconfig,os,sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()['include'],'Python.h')))" \
		|| { echo "make setup: $(PYTHON) has no C headers (Python.h), needed to build the native kernel: install python3-dev (Debian/Ubuntu) or python3-devel (Fedora)" >&2; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e 'host[dev]'
	touch $@

demo: setup
	@mkdir -p $(OUT)/demo
	host/magcal simulate --preset mems --duration 60 --seed 1 -o $(OUT)/demo/session.csv
	host/magcal calibrate $(OUT)/demo/session.csv --method ml -o $(OUT)/demo/result.json \
		--plot $(OUT)/demo/plots --truth $(OUT)/demo/session.truth.json

lint: setup
	$(VENV)/bin/ruff check host tests tools bench
	$(VENV)/bin/ruff format --check host tests tools bench

test: setup lint test-native
	$(PY) -m pytest -q tests

# The C kernel on its own (no Python) under AddressSanitizer and UndefinedBehaviorSanitizer.
NATIVE_CFLAGS := -std=c99 -O1 -g -Wall -Wextra -Wpedantic -Werror -ffp-contract=off \
	-fsanitize=address,undefined -fno-sanitize-recover=all
test-native:
	@mkdir -p build
	gcc $(NATIVE_CFLAGS) -Ihost/csrc tests/native/test_mekf_sanitizers.c \
		host/csrc/mekf_likelihood.c -lm -o build/test_mekf_sanitizers
	build/test_mekf_sanitizers

accuracy: setup
	$(PY) tools/accuracy_report.py --runs 20 --table2-runs 150 --out bench/accuracy.md --plots $(OUT)/accuracy

bench: setup
	$(PY) bench/run_bench.py --out bench/results.json

clean:
	rm -rf $(OUT) build host/build host/src/*.egg-info $(STAMP)
	find host -name '_mekf*.so' -delete
