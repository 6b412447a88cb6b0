# SPDX-License-Identifier: Apache-2.0
"""Writers of flight logs for the import tests: ArduPilot DataFlash ``.bin``
(:mod:`.dataflash`), MAVLink telemetry ``.tlog`` (:mod:`.tlog`) and PX4 ``.ulg``
(:mod:`.ulog`), fed by :mod:`.scenario`, a simulated day on the bench: rest, a hand rotation,
rest, a flight-like stretch, rest."""
