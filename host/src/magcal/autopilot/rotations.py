# SPDX-License-Identifier: Apache-2.0
"""The enumerated sensor rotations of ArduPilot and PX4, as rotation matrices.

Convention (both autopilots, checked in their sources): an enumerated rotation ``R`` maps a
vector from the sensor frame into the body frame, ``v_body = R @ v_sensor``, and
``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (Euler 3-2-1, roll applied first).

Sources checked (read with the code search tool):

- ArduPilot ``libraries/AP_Math/rotations.h`` (commit 17bcf931): the enum 0–43 and the names.
- ArduPilot ``libraries/AP_Math/vector3.cpp`` ``Vector3::rotate()`` (commit 0a7bb2df): e.g.
  ROTATION_ROLL_90 is ``tmp = z; z = y; y = -tmp`` = ``Rx(90°) v``, and
  ROTATION_PITCH_180_YAW_90 is ``(x, y, z) → (-y, -x, -z)`` = ``Rz(90°) Ry(180°) v``, which fixes
  both the direction (sensor→body) and the order (roll first, yaw last).
  ROTATION_ROLL_90_PITCH_68_YAW_293 is given there as an explicit matrix; it equals
  ``from_euler(roll 90°, pitch 68.8°, yaw 293.3°)`` to 1e-16 (the name rounds the angles; the
  ``@Values`` comment's "Yaw293Pitch68Roll180" is wrong). Its quaternion in
  ``quaternion.cpp`` ``from_rotation`` (q1 = 0.26774500…) gives the same matrix.
  ROTATION_PITCH_7 (41) is ``q = (0.99813479, 0, 0.06104854, 0)``: pitch 7°.
- PX4 ``src/lib/conversion/rotation.h`` (commit 019b5654) and ``rotation.cpp``:
  ``get_rot_matrix(rot) = Dcmf(Eulerf(roll, pitch, yaw))`` from the integer-degree table
  ``rot_lookup``. Entries 0–40 name the same rotations as ArduPilot's, **except 38**: PX4 uses
  the integer angles (90°, 68°, 293°), not ArduPilot's (90°, 68.8°, 293.3°); they differ by
  about 0.9°. That commit also lists 41–47 (ROLL_270_YAW_180 …, *not* ArduPilot's 41–43);
  older PX4 trees numbered the enum differently (commit d4120873: 26 = ROLL_270_YAW_270 …), so
  the PX4 table here is the current one and :func:`nearest` is limited to 0–40 unless asked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.calib import frames

#: ArduPilot ``enum Rotation`` 0–43: (name, roll, pitch, yaw) in degrees (rotations.h).
ARDUPILOT_TABLE: tuple[tuple[str, float, float, float], ...] = (
    ("NONE", 0, 0, 0),
    ("YAW_45", 0, 0, 45),
    ("YAW_90", 0, 0, 90),
    ("YAW_135", 0, 0, 135),
    ("YAW_180", 0, 0, 180),
    ("YAW_225", 0, 0, 225),
    ("YAW_270", 0, 0, 270),
    ("YAW_315", 0, 0, 315),
    ("ROLL_180", 180, 0, 0),
    ("ROLL_180_YAW_45", 180, 0, 45),
    ("ROLL_180_YAW_90", 180, 0, 90),
    ("ROLL_180_YAW_135", 180, 0, 135),
    ("PITCH_180", 0, 180, 0),
    ("ROLL_180_YAW_225", 180, 0, 225),
    ("ROLL_180_YAW_270", 180, 0, 270),
    ("ROLL_180_YAW_315", 180, 0, 315),
    ("ROLL_90", 90, 0, 0),
    ("ROLL_90_YAW_45", 90, 0, 45),
    ("ROLL_90_YAW_90", 90, 0, 90),
    ("ROLL_90_YAW_135", 90, 0, 135),
    ("ROLL_270", 270, 0, 0),
    ("ROLL_270_YAW_45", 270, 0, 45),
    ("ROLL_270_YAW_90", 270, 0, 90),
    ("ROLL_270_YAW_135", 270, 0, 135),
    ("PITCH_90", 0, 90, 0),
    ("PITCH_270", 0, 270, 0),
    ("PITCH_180_YAW_90", 0, 180, 90),  # same matrix as ROLL_180_YAW_270
    ("PITCH_180_YAW_270", 0, 180, 270),  # same matrix as ROLL_180_YAW_90
    ("ROLL_90_PITCH_90", 90, 90, 0),
    ("ROLL_180_PITCH_90", 180, 90, 0),
    ("ROLL_270_PITCH_90", 270, 90, 0),
    ("ROLL_90_PITCH_180", 90, 180, 0),
    ("ROLL_270_PITCH_180", 270, 180, 0),
    ("ROLL_90_PITCH_270", 90, 270, 0),
    ("ROLL_180_PITCH_270", 180, 270, 0),
    ("ROLL_270_PITCH_270", 270, 270, 0),
    ("ROLL_90_PITCH_180_YAW_90", 90, 180, 90),
    ("ROLL_90_YAW_270", 90, 0, 270),
    ("ROLL_90_PITCH_68_YAW_293", 90, 68.8, 293.3),  # the exact angles behind the name
    ("PITCH_315", 0, 315, 0),
    ("ROLL_90_PITCH_315", 90, 315, 0),
    ("PITCH_7", 0, 7, 0),
    ("ROLL_45", 45, 0, 0),
    ("ROLL_315", 315, 0, 0),
)

#: PX4 ``rot_lookup`` 0–47 (rotation.h): (name, roll, pitch, yaw), integer degrees.
PX4_TABLE: tuple[tuple[str, float, float, float], ...] = ARDUPILOT_TABLE[:38] + (
    ("ROLL_90_PITCH_68_YAW_293", 90, 68, 293),  # PX4 uses the rounded angles
    ("PITCH_315", 0, 315, 0),
    ("ROLL_90_PITCH_315", 90, 315, 0),
    ("ROLL_270_YAW_180", 270, 0, 180),
    ("ROLL_270_YAW_270", 270, 0, 270),
    ("PITCH_90_YAW_180", 0, 90, 180),
    ("PITCH_9_YAW_180", 0, 9, 180),
    ("PITCH_45", 0, 45, 0),
    ("ROLL_270_YAW_225", 270, 0, 225),
    ("ROLL_270_YAW_315", 270, 0, 315),
)

#: Highest PX4 index that docs/autopilots.md and MAV_SENSOR_ORIENTATION agree on.
PX4_MAX_COMMON_INDEX = 40
ARDUPILOT_MAX_INDEX = len(ARDUPILOT_TABLE) - 1


def euler_deg_to_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """(3, 3) sensor→body rotation ``Rz(yaw) Ry(pitch) Rx(roll)``; angles in degrees.

    This is ArduPilot's ``Matrix3::from_euler`` and PX4's ``Dcmf(Eulerf(r, p, y))``.
    """
    return frames.euler_zyx_to_matrix(
        np.deg2rad(yaw_deg), np.deg2rad(pitch_deg), np.deg2rad(roll_deg)
    )


def matrix_to_euler_deg(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in degrees, Euler 3-2-1, of a rotation (3, 3).

    roll, yaw in (-180, 180], pitch in [-90, 90]. At gimbal lock (|pitch| = 90°) roll is set
    to 0 and the whole rotation about z goes into yaw, so that the angles still reproduce R.
    """
    R = np.asarray(R, dtype=float)
    s = float(np.clip(-R[2, 0], -1.0, 1.0))
    pitch = np.arcsin(s)
    if abs(s) > 1.0 - 1e-12:
        roll = 0.0
        yaw = np.arctan2(-R[0, 1], R[1, 1])
    else:
        roll = np.arctan2(R[2, 1], R[2, 2])
        yaw = np.arctan2(R[1, 0], R[0, 0])
    return float(np.rad2deg(roll)), float(np.rad2deg(pitch)), float(np.rad2deg(yaw))


def rotation_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Angle (degrees) of the rotation ``A Bᵀ`` between two rotations (3, 3)."""
    E = np.asarray(A, dtype=float) @ np.asarray(B, dtype=float).T
    # atan2(sin, cos) rather than arccos: accurate near 0° and 180°
    sin = 0.5 * np.linalg.norm([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    cos = (np.trace(E) - 1.0) / 2.0
    return float(np.rad2deg(np.arctan2(sin, cos)))


def rotation_vector_deg(R: np.ndarray) -> np.ndarray:
    """(3,) the rotation vector of R (3, 3), degrees (axis times angle, angle in [0, 180])."""
    return np.degrees(frames.quat_to_rotvec(frames.matrix_to_quat(np.asarray(R, dtype=float))))


def _matrices(table: tuple[tuple[str, float, float, float], ...]) -> np.ndarray:
    return np.stack([euler_deg_to_matrix(r, p, y) for _, r, p, y in table])


#: (44, 3, 3) ArduPilot rotation matrices, index = COMPASS_ORIENT value.
ARDUPILOT_MATRICES = _matrices(ARDUPILOT_TABLE)
#: (48, 3, 3) PX4 rotation matrices, index = CAL_MAGn_ROT value.
PX4_MATRICES = _matrices(PX4_TABLE)


@dataclass(frozen=True)
class NearestRotation:
    """The enumerated rotation closest to a wanted one."""

    index: int
    name: str
    matrix: np.ndarray  # (3, 3)
    angle_deg: float  # angle of the remainder  R_wanted · R_enumᵀ


def ardupilot_matrix(index: int) -> np.ndarray:
    """(3, 3) matrix of ArduPilot ``COMPASS_ORIENT`` value 0–43."""
    if not 0 <= index <= ARDUPILOT_MAX_INDEX:
        raise ValueError(f"ArduPilot rotation {index} is not enumerated (0–{ARDUPILOT_MAX_INDEX})")
    return ARDUPILOT_MATRICES[index].copy()


def px4_matrix(index: int) -> np.ndarray:
    """(3, 3) matrix of PX4 ``CAL_MAGn_ROT`` value 0–47."""
    if not 0 <= index < len(PX4_TABLE):
        raise ValueError(f"PX4 rotation {index} is not enumerated (0–{len(PX4_TABLE) - 1})")
    return PX4_MATRICES[index].copy()


def nearest(R: np.ndarray, autopilot: str, max_index: int | None = None) -> NearestRotation:
    """The enumerated rotation of ``autopilot`` ("ardupilot" or "px4") nearest to R (3, 3).

    max_index : highest enumerated value the firmware accepts (default: ArduPilot 43, PX4 40).
    Ties (duplicate entries such as 14 and 26) go to the lower index.
    """
    if autopilot == "ardupilot":
        table, mats = ARDUPILOT_TABLE, ARDUPILOT_MATRICES
        top = ARDUPILOT_MAX_INDEX if max_index is None else max_index
    elif autopilot == "px4":
        table, mats = PX4_TABLE, PX4_MATRICES
        top = PX4_MAX_COMMON_INDEX if max_index is None else max_index
    else:
        raise ValueError(f"unknown autopilot {autopilot!r}: use 'ardupilot' or 'px4'")
    R = np.asarray(R, dtype=float)
    # trace(R Eᵀ) is largest for the smallest remainder angle
    traces = np.einsum("ij,kij->k", R, mats[: top + 1])
    k = int(np.argmax(traces + 1e-12 * -np.arange(top + 1)))
    return NearestRotation(k, table[k][0], mats[k].copy(), rotation_angle_deg(R, mats[k]))
