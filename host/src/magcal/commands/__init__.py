# SPDX-License-Identifier: Apache-2.0
"""The commands of the command line: one module (or small package) each, with
``add_parser(subparsers)`` setting ``run``; :func:`magcal.cli.build_parser` registers every
module here that has one. A device command covers both links in its own module: ``--port``
(a device running magcal's firmware) and ``--mavlink`` (an ArduPilot or PX4 autopilot).
Thin wrappers: the work is done in :mod:`magcal.device`, :mod:`magcal.autopilot`,
:mod:`magcal.calib` and the other packages; :mod:`magcal.commands.common` opens a link the same
way for all of them, and :mod:`magcal.ui` shows progress, tables and refusals."""
