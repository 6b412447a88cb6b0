# SPDX-License-Identifier: Apache-2.0
"""ArduPilot and PX4: compass parameters and MAVLink.

magcal gives ``m_b = D⁻¹ (y − o)`` with unit norm. This package turns ``(D, o)``, the local
field strength and the rotation in force into each autopilot's compass parameters, and back,
and talks to the vehicle:

- :mod:`magcal.autopilot.rotations`: the enumerated sensor rotations of both autopilots as
  matrices, nearest-enumerated look-up, custom Euler angles;
- :mod:`magcal.autopilot.mapping`: polar decomposition, ``to_ardupilot`` / ``to_px4``, the
  autopilots' own on-board correction (``ardupilot_correct`` / ``px4_correct``) for round
  trips, limit checks, and the heading error of a misalignment that cannot be represented;
- :mod:`magcal.autopilot.params`: parameter values on the MAVLink wire (ArduPilot casts,
  PX4 copies bytes) and in Mission Planner ``.parm`` / QGroundControl ``.params`` files;
- :mod:`magcal.autopilot.vehicle`: identity, compass numbering, streams, units, the session's
  frame, time stamps, reading the compass parameters in force;
- :mod:`magcal.autopilot.wmm`: the local field strength (World Magnetic Model, or given);
- :mod:`magcal.autopilot.connection`, :mod:`~magcal.autopilot.collect`,
  :mod:`~magcal.autopilot.flash`, :mod:`~magcal.autopilot.verify`: ``magcal info / collect /
  flash / verify --mavlink`` over :class:`magcal.link.mavlink.MavlinkClient`.

The conversions are pure numpy; the MAVLink I/O is in the client and the ``Autopilot`` of
:mod:`~magcal.autopilot.connection`.
"""
