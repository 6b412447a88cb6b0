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
"""

from tests.autopilot_emulator.emulator import STREAMS, AutopilotEmulator, EmulatorError
from tests.autopilot_emulator.personalities import CompassTruth, EmulatorTruth

__all__ = ["STREAMS", "AutopilotEmulator", "CompassTruth", "EmulatorError", "EmulatorTruth"]
