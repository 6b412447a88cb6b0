# SPDX-License-Identifier: Apache-2.0
# The product stands alone: magcal installed from host/ as a user installs it (not editable,
# so the native kernel is compiled into the wheel) into a fresh virtual environment, without
# the evaluation package, and run from a directory outside the checkout.
#
#   make check-install   simulate and calibrate work there, `magcal --help` lists no
#                        evaluation command (study), every module of the installed package
#                        imports, and nothing under host/src names magcal_evaluation
#
# The versions come from the lock (mk/deps.mk), as in CI; host/build goes first, as setuptools
# copies into it without deleting and a moved module would be installed twice. pip takes the
# dependencies from its cache after `make setup`, so this takes about a minute.

.PHONY: check-install

CHECK_INSTALL_DIR := build/check-install
CHECK_INSTALL_PY := $(CURDIR)/$(CHECK_INSTALL_DIR)/venv/bin/python

check-install:
	@! grep -rn --include='*.py' magcal_evaluation host/src \
		|| { echo "check-install: the product names magcal_evaluation (above); the evaluation imports the product, never the reverse" >&2; exit 1; }
	rm -rf $(CHECK_INSTALL_DIR) host/build
	$(PYTHON) -m venv $(CHECK_INSTALL_DIR)/venv
	PIP_CONSTRAINT=$(CURDIR)/$(LOCK) $(CHECK_INSTALL_PY) -m pip install --quiet ./host
	@set -e; work=$$(mktemp -d); trap 'rm -rf "$$work"' EXIT; cd "$$work"; \
	export -n PYTHONPATH; bin=$(CURDIR)/$(CHECK_INSTALL_DIR)/venv/bin; \
	$$bin/magcal simulate --preset mems --seed 1 -o s.csv; \
	$$bin/magcal calibrate s.csv -o r.json > calibrate.txt; \
	test -s r.json || { echo "check-install: magcal calibrate wrote no result" >&2; exit 1; }; \
	$$bin/magcal --help > help.txt; \
	if grep -qw study help.txt; then \
		echo "check-install: magcal --help lists study, an evaluation command, without the evaluation package installed" >&2; exit 1; fi; \
	$$bin/python -c "import importlib, pkgutil, magcal; \
	names = [m.name for m in pkgutil.walk_packages(magcal.__path__, 'magcal.') \
		if not m.name.endswith('.__main__')]; \
	[importlib.import_module(n) for n in names]; \
	assert magcal.__file__.startswith('$(CURDIR)/$(CHECK_INSTALL_DIR)/'), magcal.__file__; \
	print(f'check-install: {len(names)} modules of the installed magcal import')"; \
	if $$bin/python -c "import magcal_evaluation" 2>/dev/null; then \
		echo "check-install: magcal_evaluation is importable in the product's environment" >&2; exit 1; fi; \
	echo "check-install: the product installed from host/ works on its own"

TEST_EXTRA += check-install
