# SPDX-License-Identifier: Apache-2.0
# The browser tests: Debian's Chromium, headless (tests/browser).
#
#   make deps-browser   installs Debian's chromium (only when missing)
#   make screenshots    docs/img/collect-view.png from the browser test of collect --view
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

# docs/img/collect-view.png, the live page of `magcal collect --view` that README.md shows:
# the browser test of the page, run against the SIL device, keeps its last screenshot there.
.PHONY: screenshots
screenshots: setup sil deps-browser
	MAGCAL_UPDATE_SCREENSHOTS=1 $(PY) -m pytest -q -p no:xdist tests/browser/test_collect_view_browser.py
