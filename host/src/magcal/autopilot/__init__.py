"""Mapping magcal results onto ArduPilot and PX4 compass parameters (issue 6).

magcal gives ``m_b = D⁻¹ (y − o)`` with unit norm. This package turns ``(D, o)``, the local
field strength and the rotation in force into each autopilot's compass parameters, and back:

- :mod:`magcal.autopilot.rotations`: the enumerated sensor rotations of both autopilots as
  matrices, nearest-enumerated look-up, custom Euler angles;
- :mod:`magcal.autopilot.mapping`: polar decomposition, ``to_ardupilot`` / ``to_px4``, the
  autopilots' own on-board correction (``ardupilot_correct`` / ``px4_correct``) for round
  trips, limit checks, and the heading error of a misalignment that cannot be represented.

Everything here is pure numpy. Still to come (later work): talking to a vehicle over MAVLink
(collect, undo the on-board correction of streamed data, ``flash`` with back-up and
read-back, ``.parm``/``.params`` export), World Magnetic Model field strength, and importing
DataFlash/tlog/ULog files.
"""
