# SPDX-License-Identifier: Apache-2.0
"""Calibration results (``"format": "magcal-result/1"`` JSON): in memory, reading, writing.

See ``docs/contracts.md``. A result file is one JSON object with the required keys
``format, method, D, o, D_inv, m_n, dip_deg, gyro_bias, warnings``; any other key is optional
and is kept, unchanged, in :attr:`CalibrationResult.extra` (forward compatibility: a newer
writer's keys survive a read/write by an older reader).

Numbers are written with Python's ``repr`` (via :mod:`json`), so float64 values round-trip
exactly. JSON cannot hold NaN or infinity; they are rejected on writing and on reading, and so
are numbers too large for a float64 (``1e400`` reads as infinity, ``10**400`` as an int).
``m_n`` must be the direction the dip angle gives, ``(cos δ, 0, −sin δ)``, with
``−90° ≤ δ ≤ 90°``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magcal.calib.frames import field_direction
from magcal.errors import ResultFormatError
from magcal.io.session import check_writable, os_error_advice

RESULT_FORMAT = "magcal-result/1"
#: The keys every result file has, in the order they are written.
REQUIRED_KEYS = ("format", "method", "D", "o", "D_inv", "m_n", "dip_deg", "gyro_bias", "warnings")
#: ``m_n`` is a direction: its norm must be 1 to within this.
M_N_NORM_TOLERANCE = 1e-6
#: ``m_n`` must equal ``(cos δ, 0, −sin δ)`` of ``dip_deg`` to within this, per component.
M_N_DIP_TOLERANCE = 1e-6
#: A stored ``D_inv`` must satisfy ``max |D D_inv - I| <=`` this (hand-rounded files fail).
D_INV_TOLERANCE = 1e-6
#: ``D`` with a larger condition number cannot be inverted meaningfully.
D_MAX_CONDITION = 1e12
_CONSTRUCTOR = "calibration result"


class ResultFileError(ResultFormatError):
    """A result file cannot be opened, read or written (missing, a directory, no permission)."""


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """The outcome of one calibration (eq=False: numpy arrays do not compare to a bool).

    method    : "ml", "init", "two-step", "ckf", ...
    D         : (3, 3) float, calibration matrix, raw magnetometer units per unit field
    o         : (3,) float, offset, raw magnetometer units
    m_n       : (3,) float, unit-norm local field in the navigation frame
    dip_deg   : float, dip angle, degrees, positive down
    gyro_bias : (3,) float rad/s, or None for methods that do not estimate it
    warnings  : list of human-readable warnings (empty when none)
    extra     : optional keys (noise covariances, statistics, optimizer report, ...). Stored
                JSON-ready: arrays become (nested) lists and numpy scalars Python numbers, so
                a freshly computed result and one read back from a file look the same.

    Arrays are stored as read-only float64 copies. The correction is ``D_inv (y - o)``.
    """

    method: str
    D: np.ndarray
    o: np.ndarray
    m_n: np.ndarray
    dip_deg: float
    gyro_bias: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = _CONSTRUCTOR
        # object.__setattr__: the documented way to normalise fields of a frozen dataclass.
        set_ = object.__setattr__
        if not isinstance(self.method, str) or not self.method:
            raise ResultFormatError(f"{where}: method must be a non-empty string")
        set_(self, "D", _checked_array(self.D, (3, 3), "D", where))
        _check_invertible(self.D, where)
        set_(self, "o", _checked_array(self.o, (3,), "o", where))
        m_n = _checked_array(self.m_n, (3,), "m_n", where)
        norm = float(np.linalg.norm(m_n))
        if abs(norm - 1.0) > M_N_NORM_TOLERANCE:
            raise ResultFormatError(
                f"{where}: m_n must have unit norm, but |m_n| = {norm!r}; normalise it"
            )
        set_(self, "m_n", m_n)
        if isinstance(self.dip_deg, bool) or not isinstance(self.dip_deg, (int, float)):
            raise ResultFormatError(f"{where}: dip_deg must be a number, got {self.dip_deg!r}")
        try:
            dip = float(self.dip_deg)  # an int beyond float64 overflows here
        except OverflowError:
            raise ResultFormatError(f"{where}: dip_deg is too large for a float64") from None
        if not math.isfinite(dip):
            raise ResultFormatError(f"{where}: dip_deg is not finite ({dip!r})")
        if not -90.0 <= dip <= 90.0:
            raise ResultFormatError(
                f"{where}: dip_deg = {dip!r} is outside [-90, 90] degrees; a dip angle is "
                "positive down and at most 90° (a field pointing south is not a dip angle)"
            )
        expected = field_direction(np.deg2rad(dip))
        gap = float(np.abs(m_n - expected).max())
        if gap > M_N_DIP_TOLERANCE:
            raise ResultFormatError(
                f"{where}: m_n = {m_n.tolist()} does not agree with dip_deg = {dip!r}, which "
                f"gives (cos δ, 0, −sin δ) = {expected.tolist()} (max difference {gap:.3g}); "
                "the file was edited or corrupted: recompute m_n from dip_deg"
            )
        set_(self, "dip_deg", dip)
        if self.gyro_bias is not None:
            set_(self, "gyro_bias", _checked_array(self.gyro_bias, (3,), "gyro_bias", where))
        warnings = list(self.warnings) if isinstance(self.warnings, (list, tuple)) else None
        if warnings is None or not all(isinstance(w, str) for w in warnings):
            raise ResultFormatError(f"{where}: warnings must be a list of strings")
        set_(self, "warnings", warnings)
        if not isinstance(self.extra, dict):
            raise ResultFormatError(f"{where}: extra must be a dict")
        extra = {}
        for key, value in self.extra.items():
            if not isinstance(key, str) or key in REQUIRED_KEYS:
                raise ResultFormatError(
                    f"{where}: extra key {key!r} must be a string other than the required keys"
                )
            extra[key] = _json_ready(value, key, where)
        set_(self, "extra", extra)

    @property
    def D_inv(self) -> np.ndarray:
        """(3, 3) float, the correction matrix: ``m_b = D_inv (y - o)``."""
        return np.linalg.inv(self.D)


def apply_correction(result: CalibrationResult, mag: np.ndarray) -> np.ndarray:
    """Calibrated field ``m_b = D_inv (y - o)`` for every sample.

    mag : (N, 3) (or (..., 3)) float, raw magnetometer units
    returns the same shape: body frame, unit field norm when the calibration fits
    """
    mag = np.asarray(mag, dtype=np.float64)
    if mag.ndim == 0 or mag.shape[-1] != 3:
        raise ValueError(f"apply_correction: mag must have shape (N, 3), got {mag.shape}")
    # Row-vector form of D_inv (y - o): one matrix product for all samples.
    return (mag - result.o) @ result.D_inv.T


def result_to_dict(result: CalibrationResult) -> dict[str, Any]:
    """The JSON object of ``result``: required keys in contract order, then ``extra``."""
    out: dict[str, Any] = {
        "format": RESULT_FORMAT,
        "method": result.method,
        "D": result.D.tolist(),
        "o": result.o.tolist(),
        "D_inv": result.D_inv.tolist(),
        "m_n": result.m_n.tolist(),
        "dip_deg": result.dip_deg,
        "gyro_bias": None if result.gyro_bias is None else result.gyro_bias.tolist(),
        "warnings": list(result.warnings),
    }
    out.update(result.extra)
    return out


def result_from_dict(data: Any, where: str = "result") -> CalibrationResult:
    """Validate a decoded ``magcal-result/1`` object and build the result.

    where : names the source in error messages (e.g. ``"reading result cal.json"``)
    Unknown keys go to ``extra``. Raises :class:`ResultFormatError` naming the key.
    """
    if not isinstance(data, dict):
        raise ResultFormatError(f"{where}: expected a JSON object, got {type(data).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise ResultFormatError(
            f"{where}: missing required key(s) {', '.join(missing)}; "
            f"a {RESULT_FORMAT} file has {', '.join(REQUIRED_KEYS)}"
        )
    if data["format"] != RESULT_FORMAT:
        raise ResultFormatError(
            f"{where}: key 'format' is {data['format']!r}; this reader knows {RESULT_FORMAT!r}"
            ": upgrade magcal if the file is newer"
        )
    if not isinstance(data["method"], str) or not data["method"]:
        raise ResultFormatError(f"{where}: key 'method' must be a non-empty string")
    arrays = {}
    for key, shape in (("D", (3, 3)), ("D_inv", (3, 3)), ("o", (3,)), ("m_n", (3,))):
        arrays[key] = _checked_array(_json_numbers(data[key], shape, key, where), shape, key, where)
    gyro_bias = data["gyro_bias"]
    if gyro_bias is not None:
        gyro_bias = _json_numbers(gyro_bias, (3,), "gyro_bias", where)
    dip = data["dip_deg"]
    if isinstance(dip, bool) or not isinstance(dip, (int, float)):
        raise ResultFormatError(f"{where}: key 'dip_deg' must be a finite number, got {dip!r}")
    try:
        dip = float(dip)  # an int beyond float64 (10**400 is valid JSON) overflows here
    except OverflowError:
        raise ResultFormatError(
            f"{where}: key 'dip_deg' must be a finite number, got an integer too large for a "
            "float64"
        ) from None
    if not math.isfinite(dip):
        raise ResultFormatError(f"{where}: key 'dip_deg' must be a finite number, got {dip!r}")
    warnings = data["warnings"]
    if not isinstance(warnings, list) or not all(isinstance(w, str) for w in warnings):
        raise ResultFormatError(f"{where}: key 'warnings' must be a list of strings")
    _check_invertible(arrays["D"], where)
    residual = np.abs(arrays["D"] @ arrays["D_inv"] - np.eye(3)).max()
    if residual > D_INV_TOLERANCE:
        raise ResultFormatError(
            f"{where}: key 'D_inv' is not the inverse of 'D' (max |D D_inv - I| = {residual:.3g});"
            " the file was edited or corrupted: recompute D_inv"
        )
    extra = {k: v for k, v in data.items() if k not in REQUIRED_KEYS}
    for key, value in extra.items():
        _json_ready(value, key, where)  # rejects NaN/inf that Python's json lets through
    try:
        return CalibrationResult(
            method=data["method"],
            D=arrays["D"],
            o=arrays["o"],
            m_n=arrays["m_n"],
            dip_deg=dip,
            gyro_bias=gyro_bias,
            warnings=warnings,
            extra=extra,
        )
    except ResultFormatError as exc:  # e.g. m_n not unit norm: name the source, not the class
        problem = str(exc).removeprefix(f"{_CONSTRUCTOR}: ")
        raise ResultFormatError(f"{where}: {problem}") from exc


def write_result(path: str | os.PathLike, result: CalibrationResult) -> None:
    """Write ``result`` as ``magcal-result/1`` JSON (UTF-8, 2-space indent)."""
    name = os.fspath(path)
    # Encode fully before opening the file, so a failure leaves no half-written result.
    try:
        text = json.dumps(result_to_dict(result), indent=2, allow_nan=False, ensure_ascii=False)
    except ValueError as exc:  # e.g. an int in extra with more digits than Python will print
        raise ResultFormatError(f"writing result {name}: cannot encode it as JSON ({exc})") from exc
    try:
        with open(path, "w", encoding="utf-8", newline="\n") as f:
            f.write(text + "\n")
    except OSError as exc:
        raise ResultFileError(
            f"writing result {name}: {os_error_advice(exc, path, writing=True)}"
        ) from exc


def check_result_writable(path: str | os.PathLike) -> None:
    """Raise :class:`ResultFileError` unless :func:`write_result` can create ``path``.

    Call it before a long calibration, so that its result is not lost to a typo in ``-o``.
    """
    check_writable(path, "writing result", ResultFileError)


def read_result(path: str | os.PathLike) -> CalibrationResult:
    """Read and validate a ``magcal-result/1`` JSON file (errors name the file and key)."""
    where = f"reading result {os.fspath(path)}"
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as exc:
        raise ResultFormatError(
            f"{where}: not valid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from exc
    except UnicodeDecodeError as exc:
        raise ResultFormatError(f"{where}: not UTF-8 text ({exc})") from exc
    except (ValueError, RecursionError) as exc:  # an int of > 4300 digits; absurd nesting
        raise ResultFormatError(f"{where}: not a usable JSON file ({exc})") from exc
    except OSError as exc:
        raise ResultFileError(f"{where}: {os_error_advice(exc, path, writing=False)}") from exc
    return result_from_dict(data, where)


# --------------------------------------------------------------------------------------------
# Helpers


def _checked_array(value: Any, shape: tuple[int, ...], key: str, where: str) -> np.ndarray:
    """A read-only float64 copy of ``value`` with the given shape and finite entries."""
    try:
        a = np.array(value, dtype=np.float64)
    except OverflowError as exc:  # an int beyond float64, e.g. 10**400 (valid JSON)
        raise ResultFormatError(
            f"{where}: key '{key}' holds a number too large for a float64"
        ) from exc
    except (TypeError, ValueError) as exc:
        raise ResultFormatError(f"{where}: {key} must be numbers of shape {shape}") from exc
    if a.shape != shape:
        raise ResultFormatError(f"{where}: {key} must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ResultFormatError(f"{where}: {key} has non-finite entries: {a.tolist()}")
    a.flags.writeable = False
    return a


def _json_numbers(value: Any, shape: tuple[int, ...], key: str, where: str) -> Any:
    """Check that decoded JSON is nested lists of numbers of ``shape`` (no bools, strings)."""
    if not shape:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ResultFormatError(f"{where}: key '{key}' holds {value!r}, not a number")
        return value
    if not isinstance(value, list) or len(value) != shape[0]:
        raise ResultFormatError(
            f"{where}: key '{key}' must be a {'×'.join(map(str, shape))} list"
            f"{' of lists' if len(shape) > 1 else ''}, row-major; got {value!r}"
        )
    return [_json_numbers(v, shape[1:], key, where) for v in value]


def _check_invertible(D: np.ndarray, where: str) -> None:
    cond = np.linalg.cond(D)
    if not cond < D_MAX_CONDITION:  # also catches cond = inf/nan of a singular D
        raise ResultFormatError(
            f"{where}: D is singular or nearly so (condition number {cond:.3g}); "
            "the calibration did not determine it"
        )


def _json_ready(value: Any, path: str, where: str) -> Any:
    """``value`` as plain JSON types; numpy arrays and scalars are converted.

    Raises naming ``path`` (e.g. ``stats.cost``) for NaN/inf and for types JSON cannot hold.
    """
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ResultFormatError(
                f"{where}: key '{path}' holds {value!r}; JSON has no NaN or infinity: store "
                "null or a string instead"
            )
        return value
    if isinstance(value, (list, tuple)):
        return [_json_ready(v, f"{path}[{i}]", where) for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ResultFormatError(f"{where}: key '{path}' has non-string key {k!r}")
            out[k] = _json_ready(v, f"{path}.{k}", where)
        return out
    raise ResultFormatError(
        f"{where}: key '{path}' holds a {type(value).__name__}, which JSON cannot store"
    )


# --------------------------------------------------------------------------------------------
# Motor interference and further compasses (optional keys ``motor`` and ``compasses``)

#: The inputs a motor interference may follow, with the unit of ``u(t)`` each is given in.
MOTOR_INPUT_UNITS = {"current": "A", "throttle": "1"}


@dataclass(frozen=True, eq=False)
class MotorInterference:
    """The field the motors make at the compass, ``b·u(t)`` in ``y = D Rᵀ m + o + b·u(t)``.

    input     : "current" (battery current, A) or "throttle" (0…1)
    unit      : "A" or "1", the unit of u
    vector    : (3,) float, b: the session's magnetometer unit per unit of u, in the
                session's magnetometer frame
    kept      : whether the likelihood-ratio test kept it (False: the calibration did not
                find it; a flash leaves the motor compensation in force as it is)
    statistic, threshold : that test's figures (None when the result does not give them)
    """

    input: str
    unit: str
    vector: np.ndarray
    kept: bool
    statistic: float | None = None
    threshold: float | None = None


@dataclass(frozen=True, eq=False)
class CompassCalibration:
    """One compass's calibration in a result: the top-level ``D``, ``o`` for the session's
    compass, or an entry of ``compasses``. Same frame and unit as the session's magnetometer.

    compass : 1-based compass number (as ``--compass``); None when the result does not say
    D, D_inv : (3, 3);  o : (3,);  motor : the interference, or None;  warnings : strings
    """

    compass: int | None
    D: np.ndarray
    o: np.ndarray
    motor: MotorInterference | None
    warnings: tuple[str, ...] = ()

    @property
    def D_inv(self) -> np.ndarray:
        return np.linalg.inv(self.D)


def _motor_from(value: Any, key: str, where: str) -> MotorInterference | None:
    if value is None:
        return None
    if not isinstance(value, dict):
        raise ResultFormatError(f"{where}: key '{key}' must be an object, got {value!r}")
    source = value.get("input")
    if source not in MOTOR_INPUT_UNITS:
        raise ResultFormatError(
            f"{where}: key '{key}.input' is {source!r}; it must be one of "
            f"{', '.join(map(repr, MOTOR_INPUT_UNITS))}"
        )
    unit = value.get("unit", MOTOR_INPUT_UNITS[source])
    if unit != MOTOR_INPUT_UNITS[source]:
        raise ResultFormatError(
            f"{where}: key '{key}.unit' is {unit!r}; the {source} input is in "
            f"{MOTOR_INPUT_UNITS[source]!r}"
        )
    if "vector" not in value:
        raise ResultFormatError(f"{where}: key '{key}' has no 'vector'")
    vector = _checked_array(
        _json_numbers(value["vector"], (3,), f"{key}.vector", where), (3,), f"{key}.vector", where
    )
    kept = value.get("kept", True)
    if not isinstance(kept, bool):
        raise ResultFormatError(f"{where}: key '{key}.kept' must be true or false, got {kept!r}")
    figures = {}
    for name in ("statistic", "threshold"):
        v = value.get(name)
        if v is not None:
            figures[name] = float(_json_numbers(v, (), f"{key}.{name}", where))
    return MotorInterference(source, unit, vector, kept, **figures)


def result_motor(result: CalibrationResult, where: str = "result") -> MotorInterference | None:
    """The result's ``motor`` key (the session's first compass), validated; None without
    one. ResultFormatError names the key of a malformed one."""
    return _motor_from(result.extra.get("motor"), "motor", where)


def result_compasses(result: CalibrationResult, where: str = "result") -> list[CompassCalibration]:
    """Every compass the result calibrates: the top-level ``D``, ``o`` and ``motor`` first
    (compass ``session_meta.compass``), then each entry of ``compasses``. ResultFormatError
    names the key of a malformed entry, a compass given twice, or a ``D_inv`` that is not the
    inverse of its ``D``."""
    meta = result.extra.get("session_meta")
    first = None
    if isinstance(meta, dict) and meta.get("compass") is not None:
        try:
            first = int(str(meta["compass"]))
        except ValueError:
            raise ResultFormatError(
                f"{where}: key 'session_meta.compass' is {meta['compass']!r}, not a compass number"
            ) from None
    out = [
        CompassCalibration(
            first, result.D, result.o, result_motor(result, where), tuple(result.warnings)
        )
    ]
    further = result.extra.get("compasses")
    if further is None:
        return out
    if not isinstance(further, list):
        raise ResultFormatError(f"{where}: key 'compasses' must be a list, got {further!r}")
    for i, entry in enumerate(further):
        key = f"compasses[{i}]"
        if not isinstance(entry, dict):
            raise ResultFormatError(f"{where}: key '{key}' must be an object")
        missing = [k for k in ("compass", "D", "o") if k not in entry]
        if missing:
            raise ResultFormatError(f"{where}: key '{key}' lacks {', '.join(missing)}")
        n = entry["compass"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ResultFormatError(
                f"{where}: key '{key}.compass' must be a compass number (1, 2, …), got {n!r}"
            )
        if any(c.compass == n for c in out):
            raise ResultFormatError(f"{where}: compass {n} is calibrated twice ('{key}')")
        D = _checked_array(_json_numbers(entry["D"], (3, 3), f"{key}.D", where), (3, 3), "D", where)
        _check_invertible(D, f"{where}: '{key}'")
        o = _checked_array(_json_numbers(entry["o"], (3,), f"{key}.o", where), (3,), "o", where)
        if entry.get("D_inv") is not None:
            D_inv = _checked_array(
                _json_numbers(entry["D_inv"], (3, 3), f"{key}.D_inv", where), (3, 3), "D_inv", where
            )
            residual = np.abs(D @ D_inv - np.eye(3)).max()
            if residual > D_INV_TOLERANCE:
                raise ResultFormatError(
                    f"{where}: key '{key}.D_inv' is not the inverse of its 'D' (max |D D_inv - "
                    f"I| = {residual:.3g}): recompute it"
                )
        warnings = entry.get("warnings", [])
        if not isinstance(warnings, list) or not all(isinstance(w, str) for w in warnings):
            raise ResultFormatError(f"{where}: key '{key}.warnings' must be a list of strings")
        motor = _motor_from(entry.get("motor"), f"{key}.motor", where)
        out.append(CompassCalibration(n, D, o, motor, tuple(warnings)))
    return out
