# SPDX-License-Identifier: Apache-2.0
# The report's browser test: Debian's Chromium, headless (tests/browser).
#
#   make deps-browser   installs Debian's chromium (only when missing)
#
# `make test` runs deps-browser first (TEST_EXTRA) and exports MAGCAL_REQUIRE_BROWSER=1 to
# its pytest run, so there a missing Chromium fails tests/browser instead of skipping it.

.PHONY: deps-browser

BROWSER_DEB_PKGS := chromium
SUDO ?= $(if $(filter 0,$(shell id -u)),,sudo)

# Installs only what is missing, so a second run is instant and works offline.
deps-browser:
	@missing=$$(for p in $(BROWSER_DEB_PKGS); do \
		dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed$$' || echo $$p; \
	done); \
	if [ -z "$$missing" ]; then \
		echo "deps-browser: already installed: $(BROWSER_DEB_PKGS)"; \
	else \
		echo "deps-browser: installing" $$missing; \
		$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get update -q && \
		$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $$missing; \
	fi

test: export MAGCAL_REQUIRE_BROWSER := 1

TEST_EXTRA += deps-browser
