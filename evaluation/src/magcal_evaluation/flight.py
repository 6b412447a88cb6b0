# SPDX-License-Identifier: Apache-2.0
"""Flight logs through the command line, scored against their truth (``make flight``).

Two kinds of log:

- **Flights with a known error** (``../shared/flightlogs``: ArduCopter SITL flights whose
  compass 1 carries a known error, with ``NAME.truth.json`` and the scorer
  ``tools/score_flight.py``; their README describes both). Each goes through
  ``magcal import LOG -o s.csv``, ``magcal calibrate s.csv -o r.json`` and
  ``magcal flash r.json --param-file p.parm`` as a user types them, and the parameter file is
  scored beside the parameters in force, the truth and pymavlink's ``magfit_WMM.py`` (four
  option sets, each on a copy of the log that keeps compass 1 only).
- **Real logs** (``../shared/reallogs``): ``import`` and ``calibrate``; what was calibrated or
  why not, and physical-consistency figures of the parameters in force and of a calibration
  (the corrected field's strength and dip against the World Magnetic Model, the heading
  difference between compasses).

magfit's fits take minutes each, so their parameter files and timings are kept in a cache
directory keyed by the log's SHA-256, the options and pymavlink's version
(:func:`magfit_cache_key`); a rerun fits only what changed.

Units: fields in the session's unit (mG for ArduPilot), angles in degrees, motor
compensation in mG/A, times in seconds.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal.autopilot import rotations

#: The checkout's root (evaluation/src/magcal_evaluation/flight.py → four levels up).
REPO_ROOT = Path(__file__).resolve().parents[3]
#: The command a user types, from a checkout (host/magcal runs the project's environment).
MAGCAL = REPO_ROOT / "host" / "magcal"
DEFAULT_FLIGHTLOGS = REPO_ROOT.parent / "shared" / "flightlogs"
DEFAULT_REALLOGS = REPO_ROOT.parent / "shared" / "reallogs"

#: magfit_WMM's four option sets, as the flight logs' README compares them.
MAGFIT_FITS: dict[str, tuple[str, ...]] = {
    "magfit": (),
    "magfit --cmot": ("--cmot",),
    "magfit --elliptical": ("--elliptical",),
    "magfit --elliptical --cmot": ("--elliptical", "--cmot"),
}
#: One fit takes about 2 minutes on the 2-core machine; a fit that runs past this is stopped.
MAGFIT_TIMEOUT_S = 1200.0
#: import, calibrate and flash take seconds; anything past this is a hang.
MAGCAL_STEP_TIMEOUT_S = 600.0
#: The scorer parses the log (cached) and scores a few parameter files in seconds.
SCORE_TIMEOUT_S = 600.0

#: Acceptance on each flight with a known error.
SO3_MAX_DEG = 0.25
SO3_MAX_CUSTOM_ROTATION_DEG = 0.5
MAGFIT_RATIO_MAX = 0.8
MAGFIT_RATIO_APPLIES_ABOVE_DEG = 0.31
FLIGHT_RMS_FACTOR = 1.1
FLIGHT_RMS_MARGIN_DEG = 0.05
MOTOR_MAX_MGA = 0.1
COMPASS2_SO3_MAX_DEG = 0.25
COMPASS2_MOTOR_MAX_MGA = 0.1
IMPORT_CALIBRATE_MAX_S = 10.0

#: The scorer's random attitudes (its seed and count), for the compass-2 score.
SO3_ATTITUDES = 3000
SO3_SEED = 7

TRACEBACK_MARK = "Traceback (most recent call last)"


# ----------------------------------------------------------------------------- pure helpers
def first_sentence(text: str) -> str:
    """The first sentence of a refusal: its message without the ``magcal CMD:`` prefix, up
    to the first full stop followed by a capital letter (or the whole message)."""
    msg = text.strip()
    for line in msg.splitlines():
        if line.startswith("magcal ") and ": " in line:
            msg = line
            break
    msg = re.sub(r"^magcal [a-z-]+: ", "", msg)
    m = re.search(r"\.\s+(?=[A-Z])", msg)
    return msg[: m.start() + 1] if m else msg


def magfit_cache_key(log_sha256: str, options: tuple[str, ...], mag: int, version: str) -> str:
    """The cache directory's name of one magfit fit: the log (its SHA-256), which compass the
    copy keeps (``mag``, 0-based MAG instance), the options and pymavlink's version. Readable
    at a glance, and unique through a digest of all four."""
    if not re.fullmatch(r"[0-9a-f]{64}", log_sha256):
        raise ValueError(f"not a SHA-256 in hex: {log_sha256!r}")
    opts = " ".join(options)
    digest = hashlib.sha256(
        json.dumps([log_sha256, list(options), mag, version]).encode()
    ).hexdigest()
    slug = re.sub(r"[^a-z0-9]+", "-", opts.lower()).strip("-") or "plain"
    return f"{log_sha256[:16]}-mag{mag}-{slug}-{digest[:8]}"


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_param_file(path: str | os.PathLike) -> dict[str, float]:
    """An ArduPilot parameter file (``NAME,VALUE``, ``NAME VALUE``, or QGroundControl's
    ``SYS COMP NAME VALUE TYPE``) as name → value; ``#`` comments skipped."""
    out: dict[str, float] = {}
    for line in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = re.split(r"[,\s]+", line)
        if len(parts) >= 4 and parts[0].isdigit() and parts[1].isdigit():
            name, val = parts[2], parts[3]
        elif len(parts) >= 2:
            name, val = parts[0], parts[1]
        else:
            continue
        try:
            out[name.upper()] = float(val)
        except ValueError:
            continue
    return out


def _names(n: int) -> dict[str, str]:
    """ArduPilot's parameter stems of compass n (1-based): compass 1 has no number."""
    k = "" if n == 1 else str(n)
    return {
        "ofs": f"COMPASS_OFS{k}",
        "dia": f"COMPASS_DIA{k}",
        "odi": f"COMPASS_ODI{k}",
        "mot": f"COMPASS_MOT{k}",
        "scale": f"COMPASS_SCALE{k}",
        "orient": f"COMPASS_ORIENT{k}",
    }


def _vec(P: dict[str, float], stem: str, default: float) -> np.ndarray:
    return np.array([P.get(f"{stem}_{ax}", default) for ax in "XYZ"], float)


@dataclass(frozen=True)
class ApCorrection:
    """ArduPilot's correction of compass n on the vector ``y`` that ``rotate_field`` gives
    with the rotation ``R`` in force: ``c = M s (R_rel y + OFS) + MOT u``.

    M : (3, 3) the symmetric DIA/ODI matrix (identity when DIA is all zero, as ArduPilot)
    s : COMPASS_SCALE, ignored outside 0.8–1.3 (as ArduPilot's ``have_scale_factor``)
    R : (3, 3) the orientation, sensor → body
    ofs, mot : (3,) mG and mG per unit of u
    motct : 0 none, 1 throttle (0…1), 2 battery current (A)
    """

    M: np.ndarray
    s: float
    R: np.ndarray
    ofs: np.ndarray
    mot: np.ndarray
    motct: int


def orientation(P: dict[str, float], n: int) -> np.ndarray:
    """(3, 3) sensor → body rotation of compass n: COMPASS_ORIENT{n}, with 100/101 the
    custom rotation CUST_ROT1 and 102 CUST_ROT2 (roll, pitch, yaw in degrees)."""
    o = int(round(P.get(_names(n)["orient"], 0.0)))
    if o in (100, 101, 102):
        k = 2 if o == 102 else 1
        return rotations.euler_deg_to_matrix(
            P.get(f"CUST_ROT{k}_ROLL", 0.0),
            P.get(f"CUST_ROT{k}_PITCH", 0.0),
            P.get(f"CUST_ROT{k}_YAW", 0.0),
        )
    return rotations.ardupilot_matrix(o)


def ap_correction(P: dict[str, float], n: int) -> ApCorrection:
    """Compass n's correction from a parameter dictionary (names it lacks: ArduPilot's
    defaults: no offsets, identity, scale 1, no motor compensation, orientation 0)."""
    names = _names(n)
    dia = _vec(P, names["dia"], 0.0)
    odi = _vec(P, names["odi"], 0.0)
    if np.any(dia != 0.0):
        M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    else:
        M = np.eye(3)
    s = P.get(names["scale"], 1.0)
    s = s if 0.8 <= s <= 1.3 else 1.0
    motct = int(round(P.get("COMPASS_MOTCT", 0.0)))
    mot = _vec(P, names["mot"], 0.0) if motct in (1, 2) else np.zeros(3)
    return ApCorrection(M, float(s), orientation(P, n), _vec(P, names["ofs"], 0.0), mot, motct)


def apply_correction(
    corr: ApCorrection, y: np.ndarray, R_in_force: np.ndarray, u: np.ndarray | None = None
) -> np.ndarray:
    """The corrected field (N, 3), mG, of session columns ``y`` (N, 3): the compass's
    ``rotate_field`` output with the rotation in force ``R_in_force`` and nothing corrected.
    ``u`` (N,): the motor input the correction's ``motct`` asks for (None: no compensation)."""
    raw = y @ R_in_force  # rows: R_in_forceᵀ y, back to the sensor's axes
    c = (corr.s * (raw @ corr.R.T + corr.ofs)) @ corr.M.T
    if u is not None and corr.motct in (1, 2):
        c = c + np.asarray(u, float)[:, None] * corr.mot
    return c


def heading_deg(v: np.ndarray) -> np.ndarray:
    """Heading of world-frame (north, east, down) vectors (..., 3), degrees."""
    return np.degrees(np.arctan2(v[..., 1], v[..., 0]))


def wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def random_attitudes(n: int = SO3_ATTITUDES, seed: int = SO3_SEED) -> np.ndarray:
    """(n, 3, 3) body → world rotations, uniform on SO(3) (scipy's, seeded)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=seed).as_matrix()


def so3_against(
    cand: ApCorrection, ref: ApCorrection, field_ned: np.ndarray, attitudes: np.ndarray
) -> dict:
    """Heading error (deg, RMS and max) of ``cand`` against ``ref`` over ``attitudes``
    (n, 3, 3, body → world), motor interference left out: the sensor's raw reading is the one
    ``ref`` corrects exactly to the true body field (``ref`` is the truth), as the flight
    logs' scorer does for compass 1 with the simulated sensor."""
    B_body = np.einsum("nji,j->ni", attitudes, field_ned)  # Rᵀ B
    # ref: c = M s (R raw + ofs)  →  raw = Rᵀ ((M s)⁻¹ c − ofs)
    raw = (np.linalg.solve(ref.s * ref.M, B_body.T).T - ref.ofs) @ ref.R
    c = (cand.s * (raw @ cand.R.T + cand.ofs)) @ cand.M.T
    h = wrap_deg(heading_deg(np.einsum("nij,nj->ni", attitudes, c)) - heading_deg(field_ned))
    return {"so3_rms": float(np.sqrt(np.mean(h**2))), "so3_max": float(np.abs(h).max())}


def motor_error(cand: ApCorrection, ref: ApCorrection) -> float | None:
    """|MOT − MOT_ref| in mG/A for current-based compensation (no compensation counts as
    zero); None when either is throttle-based (another unit)."""
    if cand.motct == 1 or ref.motct == 1:
        return None
    a = cand.mot if cand.motct == 2 else np.zeros(3)
    b = ref.mot if ref.motct == 2 else np.zeros(3)
    return float(np.linalg.norm(a - b))


def forward_fill(x: np.ndarray) -> np.ndarray:
    """(N, k) rows with NaN replaced by the last row without (NaN before the first)."""
    x = np.asarray(x, float)
    ok = ~np.isnan(x[:, 0])
    idx = np.where(ok, np.arange(len(x)), -1)
    idx = np.maximum.accumulate(idx)
    out = np.full_like(x, np.nan)
    have = idx >= 0
    out[have] = x[idx[have]]
    return out


def dip_deg(c: np.ndarray, down: np.ndarray) -> np.ndarray:
    """The field's dip below the horizontal (deg, positive down) of body-frame fields ``c``
    (N, 3) with the unit down direction ``down`` (N, 3) in the same frame."""
    along = np.sum(c * down, axis=1)
    return np.degrees(np.arcsin(np.clip(along / np.linalg.norm(c, axis=1), -1.0, 1.0)))


def heading_difference_deg(a: np.ndarray, b: np.ndarray, down: np.ndarray) -> np.ndarray:
    """The heading of field ``b`` minus that of field ``a`` (N,), degrees, both (N, 3) in the
    body frame, measured about the down direction ``down`` (N, 3, unit): the angle between
    their horizontal parts, positive clockwise seen from above (as headings grow)."""
    ha = a - np.sum(a * down, axis=1)[:, None] * down
    hb = b - np.sum(b * down, axis=1)[:, None] * down
    # about "down", clockwise from above is the right-hand sense: a → b positive
    cross = np.sum(down * np.cross(ha, hb), axis=1)
    return np.degrees(np.arctan2(cross, np.sum(ha * hb, axis=1)))


def rms(x) -> float | None:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else None


# ----------------------------------------------------------------------------- criteria
@dataclass(frozen=True)
class Criterion:
    """One acceptance criterion on one log: passed is None where it does not apply."""

    log: str
    text: str
    measured: str
    passed: bool | None


def _num(x: float | None, fmt: str = "{:.2f}") -> str:
    return "–" if x is None else fmt.format(x)


def flight_criteria(f: dict) -> list[Criterion]:
    """The acceptance criteria of one flight from its figures (``run_flight``'s dict): magcal's
    SO(3) and in-flight heading error, motor vector, compass 2, and the time. Where magcal
    refused or failed, every criterion fails with that reason."""
    name = f["name"]
    mc = f.get("magcal") or {}
    scores = f.get("scores") or {}
    m = scores.get("magcal")
    custom = bool((f.get("truth_sim") or {}).get("ROT"))
    so3_limit = SO3_MAX_CUSTOM_ROTATION_DEG if custom else SO3_MAX_DEG
    why = None
    if m is None:
        # the refusal itself stands in the flight's table; here only where it happened
        if mc.get("refused"):
            why = f"no calibration: {mc['refused_at']} refused"
        else:
            why = mc.get("error") or "no magcal result scored"
    out: list[Criterion] = []

    def add(text: str, measured: str | None, passed: bool | None) -> None:
        out.append(Criterion(name, text, why if measured is None else measured, passed))

    so3_text = f"SO(3) RMS ≤ {so3_limit}°" + (" (custom rotation)" if custom else "")
    if m is None:
        add(so3_text, None, False)
    else:
        add(so3_text, f"{m['so3_rms']:.3f}°", m["so3_rms"] <= so3_limit)

    best = best_magfit(scores)
    ratio_text = f"SO(3) RMS ≤ {MAGFIT_RATIO_MAX}× magfit's best where that is above "
    ratio_text += f"{MAGFIT_RATIO_APPLIES_ABOVE_DEG}°"
    if best is None:
        add(ratio_text, "no magfit fit scored", None)
    elif best[1] <= MAGFIT_RATIO_APPLIES_ABOVE_DEG:
        add(ratio_text, f"magfit's best {best[1]:.3f}° ({best[0]}): does not apply", None)
    elif m is None:
        add(ratio_text, None, False)
    else:
        q = m["so3_rms"] / best[1]
        measured = f"{q:.2f}× ({m['so3_rms']:.3f}° / {best[1]:.3f}°, {best[0]})"
        add(ratio_text, measured, q <= MAGFIT_RATIO_MAX)

    ideal = scores.get("ideal")
    fl_text = f"in-flight RMS ≤ {FLIGHT_RMS_FACTOR}× the truth's + {FLIGHT_RMS_MARGIN_DEG}°"
    if m is None or ideal is None:
        add(fl_text, None if m is None else "the truth was not scored", False)
    else:
        limit = FLIGHT_RMS_FACTOR * ideal["flight_rms"] + FLIGHT_RMS_MARGIN_DEG
        add(
            fl_text,
            f"{m['flight_rms']:.3f}° (limit {limit:.3f}°)",
            m["flight_rms"] <= limit,
        )

    mot_text = f"motor vector within {MOTOR_MAX_MGA} mG/A"
    if m is None:
        add(mot_text, None, False)
    elif m.get("mot_err") is None:
        add(mot_text, "throttle-based compensation: not comparable", False)
    else:
        add(mot_text, f"{m['mot_err']:.3f} mG/A", m["mot_err"] <= MOTOR_MAX_MGA)

    c2 = f.get("compass2")
    c2_text = (
        f"compass 2 within {COMPASS2_SO3_MAX_DEG}° (SO(3)) and {COMPASS2_MOTOR_MAX_MGA} mG/A "
        "of its right calibration in force"
    )
    if m is None:
        add(c2_text, None, False)
    elif not c2 or c2.get("missing"):
        add(c2_text, (c2 or {}).get("missing") or "not in the result", False)
    else:
        mot = c2.get("mot_err")
        ok = c2["so3_rms"] <= COMPASS2_SO3_MAX_DEG and (
            mot is not None and mot <= COMPASS2_MOTOR_MAX_MGA
        )
        add(c2_text, f"{c2['so3_rms']:.3f}°, {_num(mot, '{:.3f}')} mG/A", ok)

    t_text = f"import + calibrate ≤ {IMPORT_CALIBRATE_MAX_S:g} s"
    t = (mc.get("seconds") or {}).get("import", 0.0) + (mc.get("seconds") or {}).get(
        "calibrate", 0.0
    )
    if m is None:
        add(t_text, f"{t:.1f} s, {why}", False)
    else:
        add(t_text, f"{t:.1f} s", t <= IMPORT_CALIBRATE_MAX_S)
    return out


def best_magfit(scores: dict) -> tuple[str, float] | None:
    """(label, SO(3) RMS) of magfit's fit with the lowest SO(3) RMS among those scored."""
    fits = [(k, v["so3_rms"]) for k, v in scores.items() if k in MAGFIT_FITS and v]
    return min(fits, key=lambda kv: kv[1]) if fits else None


def reallog_criterion(logs: list[dict]) -> Criterion:
    """Every real log imported and calibrated, or refused in a message: no traceback, no
    other exit status than 0 (done) and 2 (refused)."""
    bad = [
        r["name"]
        for r in logs
        if any(s.get("traceback") or s.get("rc") not in (0, 2) for s in r["steps"].values())
    ]
    return Criterion(
        "real logs",
        "every real log calibrated or refused with a message; no traceback",
        f"{len(logs)} logs" + (f"; tracebacks or crashes: {', '.join(bad)}" if bad else ""),
        not bad,
    )


# ----------------------------------------------------------------------------- running
def run_step(argv: list[str], cwd: Path, timeout_s: float, env: dict | None = None) -> dict:
    """Run one command; its exit status, wall time, stdout and stderr (tails), whether it
    printed a traceback. A time-out is reported as a failed step (rc None), not raised: one
    hung log must not hide the others' figures."""
    t0 = time.perf_counter()
    try:
        p = subprocess.run(
            argv,
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            env={**os.environ, **(env or {})},
        )
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as exc:
        rc = None
        out = exc.stdout if isinstance(exc.stdout, str) else ""
        err = (
            exc.stderr if isinstance(exc.stderr, str) else ""
        ) + f"\ntimed out after {timeout_s:g} s"
    seconds = time.perf_counter() - t0
    return {
        "argv": [str(a) for a in argv],
        "rc": rc,
        "seconds": seconds,
        "stdout": out[-4000:],
        "stderr": err[-4000:],
        "traceback": TRACEBACK_MARK in out or TRACEBACK_MARK in err,
    }


def user_command(step: dict) -> str:
    """A step's command as a user types it: ``magcal …`` for the launcher."""
    argv = list(step["argv"])
    if argv and Path(argv[0]) == MAGCAL:
        argv[0] = "magcal"
    return " ".join(argv)


def magcal_pipeline(log: Path, work: Path, flash: bool = True) -> dict:
    """``magcal import LOG -o s.csv``, ``calibrate s.csv -o r.json`` and (``flash``) ``flash
    r.json --param-file p.parm`` in ``work``, default options. Each step's record, the
    refusal's first sentence where a step refused, and the files written."""
    work.mkdir(parents=True, exist_ok=True)
    for f in ("s.csv", "r.json", "p.parm"):
        (work / f).unlink(missing_ok=True)
    steps: dict[str, dict] = {}
    out: dict = {"steps": steps, "seconds": {}, "refused": None, "refused_at": None}
    plan = [
        ("import", [MAGCAL, "import", str(log), "-o", "s.csv"]),
        ("calibrate", [MAGCAL, "calibrate", "s.csv", "-o", "r.json"]),
    ]
    if flash:
        plan.append(("flash", [MAGCAL, "flash", "r.json", "--param-file", "p.parm"]))
    for name, argv in plan:
        s = run_step(argv, work, MAGCAL_STEP_TIMEOUT_S)
        steps[name] = s
        out["seconds"][name] = s["seconds"]
        if s["rc"] != 0:
            if s["rc"] == 2 and not s["traceback"]:
                out["refused"] = first_sentence(s["stderr"])
                out["refused_at"] = name
            else:
                out["error"] = (
                    f"{name} exited with {s['rc']}"
                    + (" after a traceback" if s["traceback"] else "")
                    + ": "
                    + (s["stderr"].strip().splitlines() or ["(no message)"])[-1]
                )
            break
    out["session"] = str(work / "s.csv") if (work / "s.csv").exists() else None
    out["result"] = (
        str(work / "r.json")
        if (work / "r.json").exists() and "calibrate" in steps and steps["calibrate"]["rc"] == 0
        else None
    )
    out["param_file"] = (
        str(work / "p.parm")
        if flash and (work / "p.parm").exists() and steps.get("flash", {}).get("rc") == 0
        else None
    )
    return out


def pymavlink_version() -> str:
    from importlib.metadata import version

    return version("pymavlink")


def magfit_script() -> Path:
    return Path(sys.executable).with_name("magfit_WMM.py")


def magfit_fit(
    log: Path, log_sha256: str, label: str, cache_dir: Path, tools: Path, mag: int = 0
) -> dict:
    """One magfit_WMM fit of ``log``'s compass ``mag`` (0-based MAG instance) with the
    options of ``MAGFIT_FITS[label]``, from the cache when it holds it. The record:
    ``param_file``, ``seconds`` (the fit's wall time when it was measured), ``cached``
    (True: taken from the cache, measured on ``measured_on``), and ``error`` where it failed."""
    options = MAGFIT_FITS[label]
    version = pymavlink_version()
    key = magfit_cache_key(log_sha256, options, mag, version)
    d = cache_dir / key
    meta_path = d / "meta.json"
    if meta_path.exists() and (d / "fit.param").exists():
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        return {**meta, "param_file": str(d / "fit.param"), "cached": True, "key": key}
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    copy = d / f"m{mag}.bin"
    keep = run_step(
        [
            sys.executable,
            str(tools / "keep_mag_instance.py"),
            str(log),
            copy.name,
            "--mag",
            str(mag),
        ],
        d,
        MAGCAL_STEP_TIMEOUT_S,
    )
    record = {
        "label": label,
        "options": list(options),
        "log_sha256": log_sha256,
        "mag_instance": mag,
        "pymavlink": version,
        "keep_seconds": keep["seconds"],
        "measured_on": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "key": key,
    }
    if keep["rc"] != 0:
        return {
            **record,
            "cached": False,
            "error": "keep_mag_instance.py: " + keep["stderr"][-300:],
        }
    fit = run_step(
        [sys.executable, str(magfit_script()), *options, "--save-params", copy.name],
        d,
        MAGFIT_TIMEOUT_S,
        env={"MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"},
    )
    record["seconds"] = fit["seconds"]
    record["command"] = "MPLBACKEND=Agg magfit_WMM.py " + " ".join(
        [*options, "--save-params", copy.name]
    )
    saved = sorted(d.glob(f"m{mag}-magfit-mag-*.param"))
    copy.unlink(missing_ok=True)  # the copy is as large as the log; the cache keeps the fit
    (d / "stdout.txt").write_text(fit["stdout"], encoding="utf-8")
    if fit["rc"] != 0 or not saved:
        return {
            **record,
            "cached": False,
            "error": f"magfit_WMM.py exited with {fit['rc']}: " + fit["stderr"][-300:],
        }
    saved[0].rename(d / "fit.param")
    # meta.json last: a fit interrupted before it is not taken from the cache
    meta_path.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    return {**record, "param_file": str(d / "fit.param"), "cached": False}


# ----------------------------------------------------------------------------- consistency
def session_params(meta: dict[str, str]) -> dict[str, float]:
    """The parameters in force a session recorded (its ``param.NAME`` metadata)."""
    out = {}
    for k, v in meta.items():
        if k.startswith("param."):
            try:
                out[k[len("param.") :].upper()] = float(v)
            except ValueError:
                continue
    return out


def compass_columns(meta: dict[str, str]) -> list[tuple[int, str]]:
    """(compass number, column stem) of every compass of a session: the first is ``mag``,
    compass n after it ``mag{n}`` (the session's ``compasses`` metadata; one compass
    ``compass`` without it)."""
    text = meta.get("compasses") or meta.get("compass") or "1"
    numbers = [int(x) for x in text.split(",") if x.strip()]
    return [(n, "mag" if i == 0 else f"mag{n}") for i, n in enumerate(numbers)]


def correction_figures(
    fields: dict[int, np.ndarray], down: np.ndarray, strength: float, inclination_deg: float
) -> dict:
    """Physical consistency of corrected fields against the Earth's.

    fields : compass number → (N, 3) corrected body-frame field, mG, NaN rows where that
             compass has no sample on the row
    down   : (N, 3) unit down direction in the body frame (from the accelerometer)
    strength, inclination_deg : the World Magnetic Model's total field (mG) and inclination

    Per compass: ``strength_ratio`` (median |c| / strength), ``strength_spread`` (std/mean of
    |c|), ``dip_error_deg`` (median dip − inclination). ``heading_vs_first_deg``: compass n
    against the first compass, the RMS and median of their heading difference on rows where
    both measured.
    """
    out: dict = {"compasses": {}, "heading_vs_first_deg": {}}
    numbers = list(fields)
    for n in numbers:
        c = fields[n]
        ok = np.isfinite(c[:, 0]) & np.isfinite(down[:, 0])
        if ok.sum() < 10:
            continue
        norm = np.linalg.norm(c[ok], axis=1)
        dip = dip_deg(c[ok], down[ok])
        out["compasses"][n] = {
            "samples": int(ok.sum()),
            "strength_ratio": float(np.median(norm) / strength),
            "strength_spread": float(norm.std() / norm.mean()),
            "dip_error_deg": float(np.median(dip) - inclination_deg),
        }
    if numbers:
        first = fields[numbers[0]]
        for n in numbers[1:]:
            c = fields[n]
            ok = np.isfinite(first[:, 0]) & np.isfinite(c[:, 0]) & np.isfinite(down[:, 0])
            if ok.sum() < 10:
                continue
            d = heading_difference_deg(first[ok], c[ok], down[ok])
            out["heading_vs_first_deg"][n] = {"rms": rms(d), "median": float(np.median(d))}
    return out


def session_consistency(session_path: str, param_file: str | None) -> dict:
    """Consistency figures of an imported ArduPilot session (:func:`correction_figures`) with
    the parameters in force (``before``) and, given a parameter file (``flash
    --param-file``), with those over the ones in force (``after``). The Earth field: the World
    Magnetic Model at the session's ``location`` on its ``date``."""
    from magcal.autopilot.wmm import FieldError, wmm_field
    from magcal.io.session import read_session

    s = read_session(session_path, extra=True)
    meta = s.meta
    if meta.get("autopilot", "ardupilot") != "ardupilot":
        return {"skipped": f"{meta.get('autopilot')} parameters are not modelled here"}
    if meta.get("mag_unit", "mG") != "mG":
        return {"skipped": f"magnetometer unit {meta.get('mag_unit')} (expected mG)"}
    loc, date = meta.get("location"), meta.get("date")
    if not loc or not date:
        return {"skipped": "the session records no location or date"}
    lat, lon, *alt = (float(x) for x in loc.split(","))
    try:
        field = wmm_field(lat, lon, alt[0] if alt else 0.0, dt.date.fromisoformat(date[:10]))
    except (FieldError, ValueError) as exc:
        return {"skipped": f"World Magnetic Model: {exc}"}
    strength = field.strength("mG")
    acc = forward_fill(s.acc)
    down = -acc / np.linalg.norm(acc, axis=1)[:, None]
    columns = {"mag": s.mag}
    for _, stem in compass_columns(meta)[1:]:
        cols = [s.extra.get(f"{stem}_{ax}") for ax in "xyz"]
        if all(c is not None for c in cols):
            columns[stem] = np.column_stack(cols)
    P0 = session_params(meta)
    current = s.extra.get("current")
    throttle = s.extra.get("throttle")

    def corrected(P: dict[str, float]) -> dict[int, np.ndarray]:
        out = {}
        for n, stem in compass_columns(meta):
            if stem not in columns:
                continue
            corr = ap_correction(P, n)
            u = {2: current, 1: throttle}.get(corr.motct)
            out[n] = apply_correction(corr, columns[stem], orientation(P0, n), u)
        return out

    res = {
        "wmm": {
            "strength_mG": strength,
            "inclination_deg": field.inclination_deg,
            "source": field.source,
        },
        "before": correction_figures(corrected(P0), down, strength, field.inclination_deg),
    }
    if param_file:
        P1 = {**P0, **read_param_file(param_file)}
        res["after"] = correction_figures(corrected(P1), down, strength, field.inclination_deg)
    return res
