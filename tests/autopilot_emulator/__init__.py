# SPDX-License-Identifier: Apache-2.0
"""An autopilot emulator for the tests: ArduPilot or PX4 over MAVLink 2 on UDP loopback.

    from tests.autopilot_emulator import AutopilotEmulator
    with AutopilotEmulator(personality="ardupilot", seed=0, speedup=10.0) as emu:
        link = mavutil.mavlink_connection(emu.url)   # "udpin:127.0.0.1:PORT"
        ...
        emu.params, emu.truth, emu.field_strength, emu.heading_error_deg(compass=1)

Manual runs: ``python -m tests.autopilot_emulator --personality px4 --port 14550 --seed 1``.

Modules: :mod:`.emulator` (thread, link, messages), :mod:`.personalities` (parameters, hidden
compass errors, on-board state), :mod:`.onboard` (the autopilots' corrections from their
sources), :mod:`.params` (parameter encodings), :mod:`.world` (motion, IMU, heading error).

Units and frames of the streams (body frame = the vehicle's x forward, y right, z down):

=============  ==========  =======================================================================
message        personality content
=============  ==========  =======================================================================
RAW_IMU        ArduPilot   time_usec µs; IMU 1 accel mG (×1000/9.80665), gyro mrad/s, compass 1
                           **corrected** field mG, body frame; int16 truncated toward zero
SCALED_IMU2/3  ArduPilot   time_boot_ms; IMU 2/3 and compass 2/3 as RAW_IMU (zeros if absent)
SCALED_IMU     PX4         time_boot_ms; IMU 1 accel mG, gyro mrad/s (body, calibrated), compass 1
SCALED_IMU2/3  PX4         **raw** sensor_mag: sensor frame, gauss × 1000 = mG (SCALED_IMU.hpp)
HIGHRES_IMU    PX4         time_usec; accel m/s², gyro rad/s, compass 1 **corrected** field gauss,
                           body frame (vehicle_magnetometer, estimator bias 0)
ATTITUDE       both        time_boot_ms; true roll/pitch/yaw of the body relative to NED, rad
                           (yaw from magnetic north: declination 0), body rates rad/s
=============  ==========  =======================================================================

Times are those of the simulated sample a message carries (sample k at k / 200 s); streams are
off until MAV_CMD_SET_MESSAGE_INTERVAL (interval µs; 0 = default = off, −1 = off; at most the
200 Hz sample rate). HEARTBEAT at 1 Hz of simulated time (MAV_TYPE_QUADROTOR,
MAV_AUTOPILOT_ARDUPILOTMEGA or MAV_AUTOPILOT_PX4, system 1, component 1).

Compasses (``compasses`` = 1–3; the parameters of three are always listed): compass 1 is
external (ArduPilot COMPASS_EXTERNAL = 1, PX4 CAL_MAG0_ROT ≥ 0) with an enumerated mounting
rotation and, on ArduPilot, a hidden 3° misalignment; compasses 2 and 3 are internal. PX4's
sensor_mag instance n − 1 is calibrated by CAL_MAG{n − 1}. ``emu.truth.compass(n)`` gives
``D``, ``o`` for ``y = D m_b + o`` with y the raw sensor-frame field (ArduPilot: what
``magcal.autopilot.mapping.ardupilot_uncorrect`` recovers; PX4: SCALED_IMU's field / 1000).

When parameters take effect (as in the sources, see :mod:`.onboard`):

- ArduPilot: at once, except the custom rotations: CUST_ROT1_*/CUST_ROT2_* exist only once
  CUST_ROT_ENABLE = 1, and a custom rotation's matrix is built when COMPASS_ORIENT first
  selects it (101/102) and kept until a reboot. So write CUST_ROT_ENABLE, then the
  CUST_ROTn angles, then COMPASS_ORIENT; or reboot after writing.
- PX4: each write re-reads the calibration, but an offset, diagonal or off-diagonal vector
  that differs from the one in use by ≤ 0.01 is ignored until a reboot (and an off-diagonal
  vector shorter than 0.01 is never taken). Reboot after writing.
- A reboot is MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN with param1 = 1 (or ``emu.reboot()``): the
  on-board state is rebuilt from the parameters; the clock and the link go on.
"""

from tests.autopilot_emulator.emulator import STREAMS, AutopilotEmulator, EmulatorError
from tests.autopilot_emulator.personalities import CompassTruth, EmulatorTruth

__all__ = ["STREAMS", "AutopilotEmulator", "CompassTruth", "EmulatorError", "EmulatorTruth"]
