# SPDX-License-Identifier: Apache-2.0
# Python dependencies: installs come from a lock file, so that CI, the team and users of a
# checkout get the versions CI tested. host/pyproject.toml keeps its ranges for people who
# install the package into an environment of their own.
#
#   make lock          refresh host/requirements.lock: the newest versions the ranges allow,
#                      resolved in a clean virtual environment (commit the result)
#   make test-latest   install the newest allowed versions into build/latest-venv and run the
#                      pytest suite there; reports what they break, never fails
#
# PIP_CONSTRAINT (not -c) so that the lock also holds in pip's isolated build environment:
# the native kernel is compiled with the locked setuptools too.

.PHONY: lock test-latest

LOCK := host/requirements.lock
LOCK_VENV := build/lock-venv
LATEST_VENV := build/latest-venv
LATEST_LOG := build/latest/pytest.log
# Packages of this repository, left out of the lock.
LOCK_OWN := magcal magcal-evaluation
# pip's own output names its index and find-links locations; keep only what matters.
PIP_QUIET := --quiet --disable-pip-version-check

lock:
	rm -rf $(LOCK_VENV) host/build
	$(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/python -m pip install $(PIP_QUIET) --upgrade pip setuptools
	$(LOCK_VENV)/bin/python -m pip install $(PIP_QUIET) './host[dev]' $(wildcard ./evaluation)
	@{ echo "# The versions make setup installs (pip install with PIP_CONSTRAINT=$(LOCK))."; \
	   echo "# Made by \`make lock\` from host/pyproject.toml's ranges with $$($(LOCK_VENV)/bin/python -V)"; \
	   echo "# on $$(date -u +%Y-%m-%d); refresh with \`make lock\`, run \`make test\`, commit."; \
	   $(LOCK_VENV)/bin/python -m pip freeze --all $(addprefix --exclude ,$(LOCK_OWN)); } > $(LOCK).new
	mv $(LOCK).new $(LOCK)
	@echo "lock: wrote $(LOCK) ($$(grep -vc '^#' $(LOCK)) packages)"

# host/build is removed first: setuptools copies into it without deleting, and a module that
# moved would otherwise be installed twice.
$(LATEST_VENV)/.installed: host/pyproject.toml host/setup.py evaluation/pyproject.toml
	rm -rf $(LATEST_VENV) host/build
	$(PYTHON) -m venv $(LATEST_VENV)
	$(LATEST_VENV)/bin/python -m pip install $(PIP_QUIET) --upgrade pip setuptools
	$(LATEST_VENV)/bin/python -m pip install $(PIP_QUIET) --upgrade --upgrade-strategy eager \
		'./host[dev]'
	$(LATEST_VENV)/bin/python -m pip install $(PIP_QUIET) --no-deps -e evaluation
	touch $@

# The suite runs against the non-editable install of the product in LATEST_VENV (tests import
# magcal from there, the tests package from the checkout; the evaluation, which finds the SIL
# device in its checkout, is installed editable; the few tests that run host/magcal use .venv).
# Its verdict is printed, not returned, and not as pytest's closing line, so that a CI log's
# verdict stays `make test`'s. It runs the tests that exercise the libraries directly: the
# unit tests (numpy, scipy, cvxpy, rich, pyserial), the protocol and firmware bindings, and
# the MAVLink emulator (pymavlink). Left out, as `make test` runs them on the locked
# versions and they add minutes without touching a library the unit tests do not: the
# autopilot SITL (minutes of simulated flight), the SIL device, the accuracy checks, the
# real recordings and the browser.
# When every version installed there is the locked one (the lock is fresh), the suite would
# run on exactly the libraries `make test` runs it on, so it is not run twice: the target says
# so and stops (the product installed without the editable link is `make check-install`'s).
# Like `make test`, it runs PYTEST_WORKERS processes (the Makefile).
LATEST_TESTS := tests/unit tests/protocol tests/firmware tests/autopilot
LATEST_FREEZE := $(dir $(LATEST_LOG))freeze.txt
test-latest: setup firmware-lib sil
	@mkdir -p $(dir $(LATEST_LOG))
	@if ! $(MAKE) --no-print-directory $(LATEST_VENV)/.installed > $(dir $(LATEST_LOG))install.log 2>&1; then \
		echo "test-latest: installing the newest allowed versions failed (see $(dir $(LATEST_LOG))install.log):"; \
		grep -v 'WARNING: Location' $(dir $(LATEST_LOG))install.log | tail -5; exit 0; fi
	@if ! $(LATEST_VENV)/bin/python -m pip freeze --all $(addprefix --exclude ,$(LOCK_OWN)) \
			> $(LATEST_FREEZE) 2>/dev/null || [ ! -s $(LATEST_FREEZE) ]; then \
		echo "test-latest: pip freeze listed nothing in $(LATEST_VENV); running the suite"; \
	else \
		grep -vxFf $(LOCK) $(LATEST_FREEZE) > $(LATEST_FREEZE).newer; found=$$?; \
		if [ $$found -eq 1 ]; then \
			echo "test-latest: the newest allowed versions are the locked ones ($$(wc -l < $(LATEST_FREEZE)) packages), on which make test runs the suite: not run twice"; \
			exit 0; fi; \
		sed 's/^/test-latest: newer than the lock: /' $(LATEST_FREEZE).newer; \
	fi; \
	status=0; timeout 900 $(LATEST_VENV)/bin/python -m pytest -q -p no:cacheprovider \
		-n $(PYTEST_WORKERS) $(LATEST_TESTS) > $(LATEST_LOG) 2>&1 \
		|| status=$$?; \
	summary=$$(tail -1 $(LATEST_LOG)); \
	echo "test-latest: with the newest allowed versions the suite ended with status $$status ($$summary)"; \
	grep -E '^(FAILED|ERROR) ' $(LATEST_LOG) | head -20 | sed 's/^/test-latest:   /'; \
	echo "test-latest: full log in $(LATEST_LOG); this target never fails"
