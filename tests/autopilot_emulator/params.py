# SPDX-License-Identifier: Apache-2.0
"""Parameter storage and the two autopilots' encodings of PARAM_VALUE / PARAM_SET.

ArduPilot (``libraries/GCS_MAVLink/GCS_Param.cpp``, ``AP_Param::set_float``):

- PARAM_VALUE carries every value *cast* to float (``cast_to_float``), with
  ``param_type`` MAV_PARAM_TYPE_INT8 / INT16 / INT32 for AP_Int8/16/32 and REAL32 for AP_Float;
- PARAM_SET: the float is converted with ``set_float``: integers get ±0.01 added (away from
  zero), are constrained to the type's range and truncated; floats are stored as float32. An
  unknown name, NaN or ±inf is ignored: **no answer at all** (no PARAM_ERROR, no STATUSTEXT).
  Otherwise the new value goes out in a PARAM_VALUE with ``param_index`` −1 (65535 on the
  wire, ``send_parameter_value``);
- PARAM_REQUEST_READ of an unknown name or index: no answer.
- Parameters of a group whose enable parameter is 0 (``AP_PARAM_FLAG_ENABLE``, here
  CUST_ROT1_* / CUST_ROT2_* behind CUST_ROT_ENABLE) are invisible: not listed, not counted,
  not readable or settable, until it is set to 1 (visible at once).

PX4 (``src/modules/mavlink/mavlink_parameters.cpp``):

- PARAM_VALUE copies the parameter's 4 bytes into the float field (``param_get(param,
  &msg.param_value)``): INT32 values are *bytewise* encoded (``param_type`` = 6 =
  MAV_PARAM_TYPE_INT32), floats are REAL32 (9); a client must reinterpret the float's bytes
  as a little-endian int32 for INT32 parameters;
- PARAM_SET copies the 4 bytes back (``param_set(param, &set.param_value)``) whatever
  ``param_type`` says; an unknown name gets STATUSTEXT "[pm] unknown param: NAME" and no
  PARAM_VALUE;
- PARAM_REQUEST_READ of an unknown name: no answer; of an unknown index: STATUSTEXT
  "[pm] unknown param ID: N";
- PARAM_REQUEST_LIST first sends "_HASH_CHECK" (MAV_PARAM_TYPE_UINT32, index −1), then the
  parameters in name order with their index.

PARAM_ERROR (a newer message of the development dialect) is sent by neither.

Bit patterns that are signalling NaNs as float32 (int32 values in [−8388607, −4194305] and
[2139095041, 2143289343]) do not survive a Python float; the emulator writes and reads the raw
payload bytes, so they are exact on the wire, but a pymavlink client that reads
``msg.param_value`` gets a quiet NaN for them. No parameter here uses such a value.
"""

from __future__ import annotations

import math
import struct
import threading
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

INT8 = mavlink.MAV_PARAM_TYPE_INT8
INT16 = mavlink.MAV_PARAM_TYPE_INT16
INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32

_INT_RANGES = {INT8: (-128, 127), INT16: (-32768, 32767), INT32: (-(2**31), 2**31 - 1)}
#: ArduPilot's enable-flag groups: parameter-name prefix → enable parameter.
AP_ENABLE_GROUPS = {"CUST_ROT1_": "CUST_ROT_ENABLE", "CUST_ROT2_": "CUST_ROT_ENABLE"}


@dataclass(frozen=True)
class ParamSpec:
    name: str
    mav_type: int
    default: float


def float32(x: float) -> float:
    """x rounded to the nearest float32, as a Python float."""
    return float(np.float32(x))


def ap_set_float(value: float, mav_type: int) -> float | None:
    """AP_Param::set_float: the value ArduPilot stores for a PARAM_SET value (None: ignored)."""
    if math.isnan(value) or math.isinf(value):
        return None
    if mav_type == REAL32:
        return float32(value)
    lo, hi = _INT_RANGES[mav_type]
    # "add a small amount before casting parameter values from float to integer to avoid
    # truncating to the next lower integer value"
    v = value + (0.01 if value >= 0 else -0.01)
    return float(int(min(max(v, lo), hi)))  # int() truncates toward zero, as a C cast


def int32_as_float_bytes(value: int) -> bytes:
    """The 4 bytes PX4 puts in the float field for an INT32 parameter."""
    return struct.pack("<i", int(value))


class ParamStore:
    """Thread-safe name → value store with a personality's visibility and set rules.

    personality : "ardupilot" (declaration order, set_float rules, enable groups) or "px4"
    (name order, bytewise INT32). Values are Python floats holding the stored value exactly
    (integers exactly, floats rounded to float32).
    """

    def __init__(self, personality: str, specs: list[ParamSpec]) -> None:
        if personality not in ("ardupilot", "px4"):
            raise ValueError(f"unknown personality {personality!r}")
        self.personality = personality
        ordered = sorted(specs, key=lambda s: s.name) if personality == "px4" else list(specs)
        self._types = {s.name: s.mav_type for s in ordered}
        if len(self._types) != len(ordered):
            raise ValueError("duplicate parameter names")
        self._order = [s.name for s in ordered]
        self._values = {s.name: self._stored(s.default, s.mav_type) for s in ordered}
        self._lock = threading.Lock()

    @staticmethod
    def _stored(value: float, mav_type: int) -> float:
        return float32(value) if mav_type == REAL32 else float(int(value))

    # -- views ---------------------------------------------------------------------------
    def snapshot(self) -> dict[str, float]:
        """All parameters (visible or not) → value, a copy."""
        with self._lock:
            return dict(self._values)

    def visible_names(self) -> list[str]:
        with self._lock:
            return [n for n in self._order if self._visible(n)]

    def _visible(self, name: str) -> bool:
        if self.personality != "ardupilot":
            return True
        for prefix, enable in AP_ENABLE_GROUPS.items():
            if name.startswith(prefix):
                return self._values.get(enable, 0.0) != 0.0
        return True

    def lookup(self, name: str) -> tuple[float, int] | None:
        """(value, MAV_PARAM_TYPE) of a visible parameter, else None."""
        with self._lock:
            if name in self._values and self._visible(name):
                return self._values[name], self._types[name]
        return None

    def by_index(self, index: int) -> str | None:
        names = self.visible_names()
        return names[index] if 0 <= index < len(names) else None

    def index_of(self, name: str) -> int:
        return self.visible_names().index(name)

    def type_of(self, name: str) -> int:
        return self._types[name]

    # -- changes -------------------------------------------------------------------------
    def force(self, name: str, value: float) -> None:
        """Set a value as the autopilot itself does (no wire rules, no visibility check)."""
        with self._lock:
            self._values[name] = self._stored(value, self._types[name])

    def set_from_wire(self, name: str, value_bytes: bytes) -> float | None:
        """Apply a PARAM_SET whose float field holds ``value_bytes`` (4 bytes, little-endian).
        Returns the stored value, or None when the autopilot ignores the request."""
        with self._lock:
            if name not in self._values or not self._visible(name):
                return None
            mav_type = self._types[name]
            if self.personality == "px4":
                if mav_type == INT32:
                    stored = float(struct.unpack("<i", value_bytes)[0])
                else:
                    stored = float(struct.unpack("<f", value_bytes)[0])
            else:
                stored = ap_set_float(struct.unpack("<f", value_bytes)[0], mav_type)
                if stored is None:
                    return None
            self._values[name] = stored
            return stored

    def wire_value(self, name: str) -> tuple[bytes, int]:
        """(4 bytes of the PARAM_VALUE float field, param_type) for a parameter."""
        with self._lock:
            value, mav_type = self._values[name], self._types[name]
        if self.personality == "px4" and mav_type == INT32:
            return int32_as_float_bytes(int(value)), mav_type
        return struct.pack("<f", value), mav_type
