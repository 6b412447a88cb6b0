# SPDX-License-Identifier: Apache-2.0
# magcal on flight logs (bench/flight.md): every log of FLIGHTLOGS (../shared/flightlogs beside
# the checkout by default: ArduCopter flights with a known compass error, their truth and
# scorer) through `magcal import`, `calibrate` and `flash --param-file`, scored beside the
# parameters in force, the truth and pymavlink's magfit_WMM.py (four option sets), and every
# log of REALLOGS (../shared/reallogs) through import and calibrate. magfit's fits (about two
# minutes each) are cached in $(OUT)/flight/cache, keyed by the log's SHA-256, the options and
# pymavlink's version: a rerun fits only what changed. Exits 1 when an acceptance criterion
# fails, after writing. Not part of `make test`.
#
#   make flight                      the report, the raw figures in $(OUT)/flight.json
#   make flight FLIGHTLOGS=DIR REALLOGS=DIR FLIGHT_WORKERS=1

.PHONY: flight

FLIGHTLOGS ?= ../shared/flightlogs
REALLOGS ?= ../shared/reallogs
# magfit fits at a time: one per core of the 2-core machine.
FLIGHT_WORKERS ?= 2

flight: setup
	$(PY) -m magcal_evaluation.flight_report --flights $(FLIGHTLOGS) --reallogs $(REALLOGS) \
		--workers $(FLIGHT_WORKERS) --out bench/flight.md --raw $(OUT)/flight.json \
		--work $(OUT)/flight
