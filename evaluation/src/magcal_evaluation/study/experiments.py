# SPDX-License-Identifier: Apache-2.0
"""The study's experiments: their settings, their tasks and the run of one task.

Three experiments (``magcal study --experiments``):

``figure8``
    Kok & Schön (2016) Section 8 with the Table 2 settings (``preset("table2")``): the
    heading RMSE of the calibration EKF run with the initial and with the ML estimate against
    the true attitude (their Figure 8). One run is :func:`magcal_evaluation.accuracy.run_table2`,
    the same code ``make accuracy`` runs, so the seeds 1..150 give the same numbers there.
``zhao-table1``
    Zhao et al. Table 1: mean ``A`` and ``b`` of the CKF and of TWO-STEP over 50 runs of
    their simulation (:mod:`magcal_evaluation.study.zhao`), and their Figure 1 (field norm
    before and after) from the first run.
``comparison``
    Every calibration method :func:`magcal.calib.calibrate.calibrate` accepts among
    :data:`STUDY_METHODS`, on the same seeded sessions of each scenario: the
    calibration-induced heading error (:func:`magcal_evaluation.accuracy.heading_rms_deg`), the
    time of the ``calibrate`` call, and its failures (exceptions, and refusals by the
    observability checks) with their reasons. A method appears as soon as ``calibrate``
    accepts it.

Seeds: run ``i`` (0-based) of an experiment uses seed ``settings.seed + i``; every method of
the comparison sees the same sessions. A run's result depends only on its task (experiment,
scenario, method, seed), so the job count and the order change nothing.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass

import numpy as np

import magcal_evaluation.study.zhao as zhao
from magcal import __version__
from magcal.calib import calibrate
from magcal.errors import InsufficientDataError, MagcalError
from magcal.sim.scenarios import PRESETS, preset, simulate
from magcal_evaluation import accuracy
from magcal_evaluation.study.runner import Task

STUDY_FORMAT = "magcal-study/1"
EXPERIMENTS = ("figure8", "zhao-table1", "comparison")
#: The methods the comparison runs, when ``calibrate`` accepts them.
STUDY_METHODS = ("init", "ml", "ckf", "two-step")
#: The comparison's scenarios (presets of :mod:`magcal.sim.scenarios`): the paper's Table 2,
#: slow MEMS tumbling, hand-held with a magnet and 1 m/s² accelerations, raw counts.
DEFAULT_SCENARIOS = ("table2", "mems", "handheld", "raw-counts")
DEFAULT_RUNS = 150
#: Zhao Table 1: the CKF starts from a sphere through this many first samples (see
#: :func:`_zhao_estimators`).
ZHAO_CKF_START_SAMPLES = 100
DEFAULT_SEED = 1


class StudySettingsError(MagcalError):
    """The study's settings are not usable (unknown experiment or scenario, no runs)."""


def available_methods() -> tuple[str, ...]:
    """The methods of :data:`STUDY_METHODS` that ``calibrate`` accepts in this build."""
    return tuple(m for m in STUDY_METHODS if m in calibrate.METHODS)


def zhao_estimators_available() -> bool:
    """Whether this build has the incremental CKF and TWO-STEP that Table 1 needs."""
    return _zhao_estimators() is not None


@dataclass(frozen=True)
class StudySettings:
    """What a study is; saved in its folder so that a resume can be checked against it.

    runs        : runs of ``figure8`` and, per scenario and method, of ``comparison``
    zhao_runs   : runs of ``zhao-table1`` (the paper's 50)
    seed        : the first seed; run i uses seed + i
    experiments : subset of :data:`EXPERIMENTS`, in that order
    methods     : the comparison's methods (those ``calibrate`` accepts)
    scenarios   : the comparison's scenarios (preset names)
    """

    runs: int = DEFAULT_RUNS
    zhao_runs: int = zhao.RUNS
    seed: int = DEFAULT_SEED
    experiments: tuple[str, ...] = EXPERIMENTS
    methods: tuple[str, ...] = STUDY_METHODS
    scenarios: tuple[str, ...] = DEFAULT_SCENARIOS

    def as_json(self) -> dict:
        return {
            "format": STUDY_FORMAT,
            "runs": self.runs,
            "zhao_runs": self.zhao_runs,
            "seed": self.seed,
            "experiments": list(self.experiments),
            "methods": list(self.methods),
            "scenarios": list(self.scenarios),
            "zhao_samples": zhao.SAMPLES,
        }


def make_settings(
    runs: int = DEFAULT_RUNS,
    zhao_runs: int = zhao.RUNS,
    seed: int = DEFAULT_SEED,
    experiments: tuple[str, ...] | None = None,
    scenarios: tuple[str, ...] = DEFAULT_SCENARIOS,
) -> tuple[StudySettings, list[str]]:
    """Checked settings for this build, and notes on what cannot run in it.

    experiments None means every experiment this build can run; an experiment asked for by
    name that cannot run is refused. The comparison's methods are those ``calibrate``
    accepts.
    """
    if runs < 1 or zhao_runs < 1:
        raise StudySettingsError(
            f"study: --runs and --zhao-runs must be ≥ 1, got {runs}, {zhao_runs}"
        )
    if seed < 0:
        raise StudySettingsError(f"study: --seed must be ≥ 0, got {seed}")
    notes = []
    methods = available_methods()
    missing = [m for m in STUDY_METHODS if m not in methods]
    if missing:
        notes.append(
            f"method(s) {', '.join(missing)} not compared: calibrate() in this build accepts "
            f"only {', '.join(calibrate.METHODS)}"
        )
    if experiments is None:
        experiments = tuple(
            e for e in EXPERIMENTS if e != "zhao-table1" or zhao_estimators_available()
        )
        if "zhao-table1" not in experiments:
            notes.append(
                "zhao-table1 not run: this build has no incremental CKF and TWO-STEP "
                "(magcal.calib.norm_only.ckf, magcal.calib.norm_only.twostep)"
            )
    unknown = [e for e in experiments if e not in EXPERIMENTS]
    if unknown:
        raise StudySettingsError(
            f"study: unknown experiment(s) {', '.join(unknown)}; choose from "
            f"{', '.join(EXPERIMENTS)}"
        )
    if not experiments:
        raise StudySettingsError(
            f"study: no experiment given; choose from {', '.join(EXPERIMENTS)}"
        )
    if "zhao-table1" in experiments and not zhao_estimators_available():
        raise StudySettingsError(
            "study: zhao-table1 needs the incremental CKF and TWO-STEP "
            "(magcal.calib.norm_only.ckf, magcal.calib.norm_only.twostep), which this build does "
            "not have; leave it out"
        )
    bad = [s for s in scenarios if s not in PRESETS]
    if bad or not scenarios:
        raise StudySettingsError(
            f"study: unknown scenario(s) {', '.join(bad) or '(none given)'}; choose from "
            f"{', '.join(PRESETS)}"
        )
    ordered = tuple(e for e in EXPERIMENTS if e in experiments)
    if "comparison" not in ordered:
        # Not part of this study: a later build with more methods must not block its resume.
        methods, scenarios = (), ()
        notes = [n for n in notes if not n.startswith("method(s)")]
    settings = StudySettings(runs, zhao_runs, seed, ordered, methods, tuple(scenarios))
    return settings, notes


def seeds(settings: StudySettings, experiment: str) -> list[int]:
    n = settings.zhao_runs if experiment == "zhao-table1" else settings.runs
    return [settings.seed + i for i in range(n)]


def tasks(settings: StudySettings) -> list[Task]:
    """Every run of the study, the slow ones first (so the workers end together)."""
    out: list[Task] = []
    if "comparison" in settings.experiments:
        for scenario in settings.scenarios:
            for method in settings.methods:
                for seed in seeds(settings, "comparison"):
                    out.append(
                        Task(
                            f"comparison/{scenario}/{method}/seed={seed}",
                            "comparison",
                            {"scenario": scenario, "method": method, "seed": seed},
                        )
                    )
    if "zhao-table1" in settings.experiments:
        first = settings.seed
        for seed in seeds(settings, "zhao-table1"):
            out.append(
                Task(
                    f"zhao-table1/seed={seed}",
                    "zhao-table1",
                    {"seed": seed, "traces": seed == first},
                )
            )
    if "figure8" in settings.experiments:
        for seed in seeds(settings, "figure8"):
            out.append(Task(f"figure8/seed={seed}", "figure8", {"seed": seed}))
    return out


# --------------------------------------------------------------------------------------------
# One run of each experiment: plain-number dicts. "failed": True with a "reason" marks a run
# that did not give its figures.


def run_figure8(seed: int) -> dict:
    """Kok & Schön Table 2 settings, seed ``seed``: :func:`accuracy.run_table2` (EKF heading
    RMSE with the initial and the ML estimate, ``ekf_init_deg`` / ``ekf_ml_deg``, and the
    calibration-induced heading errors ``init_deg`` / ``ml_deg`` / ``floor_deg``)."""
    out = accuracy.run_table2(seed)
    reason = out.get("error") or out.get("ekf_error")
    out["failed"] = reason is not None
    if reason is not None:
        out["reason"] = reason
    return out


def run_comparison(scenario: str, method: str, seed: int) -> dict:
    """One method on one seeded session of ``scenario``: heading error (degrees, RMS over
    the SO(3) grid), the known-attitude floor, and the seconds of the ``calibrate`` call.
    A refusal by the observability checks is recorded as such (``refused``), not forced."""
    session, truth = simulate(preset(scenario), seed)
    out: dict = {"floor_deg": accuracy.floor_heading_rms_deg(session, truth), "failed": False}
    t0 = time.perf_counter()
    try:
        cal = calibrate.calibrate(session, method)
    except InsufficientDataError as exc:
        out.update(failed=True, refused=True, reason=f"refused: {exc}")
    except Exception as exc:  # a method's failure is what the comparison counts
        out.update(failed=True, refused=False, reason=f"{type(exc).__name__}: {exc}")
    else:
        out["heading_deg"] = accuracy.heading_rms_deg(truth, cal.result.D, cal.result.o)
        out["warnings"] = len(cal.result.warnings)
    out["seconds"] = time.perf_counter() - t0
    return out


def run_zhao(seed: int, traces: bool) -> dict:
    """Zhao et al.'s simulation with ``seed``: ``A`` and ``b`` (gauss) of the CKF and of
    TWO-STEP, their seconds, and with ``traces`` the field norms of their Figure 1."""
    estimators = _zhao_estimators()
    if estimators is None:
        raise MagcalError("zhao-table1: this build has no incremental CKF and TWO-STEP")
    y = zhao.simulate_zhao(np.random.default_rng(seed))
    out: dict = {"failed": False, "samples": int(y.shape[0])}
    if traces:
        out["norm_raw"] = np.linalg.norm(y, axis=1).tolist()
    reasons = []
    for name, estimate in estimators.items():
        t0 = time.perf_counter()
        try:
            A, b = estimate(y)
        except Exception as exc:
            reasons.append(f"{name}: {type(exc).__name__}: {exc}")
            out[name] = {"failed": True, "reason": reasons[-1]}
            continue
        seconds = time.perf_counter() - t0
        out[name] = {"A": np.asarray(A).tolist(), "b": np.asarray(b).tolist(), "seconds": seconds}
        if traces:
            out[name]["norm"] = zhao.calibrated_norms(y, A, b).tolist()
    if reasons:
        out["failed"] = True
        out["reason"] = "; ".join(reasons)
    return out


def _zhao_estimators() -> dict | None:
    """{"ckf": y ↦ (A, b), "two-step": y ↦ (A, b)} in the paper's units (gauss, ``(y − b)ᵀ A
    (y − b) = B_m²``), or None when this build lacks the CKF and TWO-STEP modules.

    The CKF is the incremental :class:`~magcal.calib.norm_only.ckf.CubatureCalibrator`, fed one
    sample at a time; TWO-STEP is :func:`~magcal.calib.norm_only.twostep.two_step`. Both get the
    simulation's σ, as the paper's filter is given ``N_k``: their own estimate from second
    differences assumes consecutive samples of a smooth motion, which the paper's independent
    random attitudes are not. The CKF starts from the sphere of its first
    :data:`ZHAO_CKF_START_SAMPLES` samples (a :class:`~magcal.calib.norm_only.ckf.CkfPrior`): its
    default start waits for readings spread by ≥ 5σ in every direction, which at the paper's
    σ (10 % of the field) never comes. magcal's ``A`` is for a unit field norm; the paper's
    is ``B_m²`` times it.
    """
    try:
        ckf = importlib.import_module("magcal.calib.norm_only.ckf")
        twostep = importlib.import_module("magcal.calib.norm_only.twostep")
    except ImportError:
        return None
    scale = zhao.field_norm_g() ** 2

    def run_ckf(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        prior = ckf.CkfPrior.from_readings(y[:ZHAO_CKF_START_SAMPLES])
        calibrator = ckf.CubatureCalibrator(prior, noise_std=zhao.NOISE_SIGMA_G)
        calibrator.update_many(y)  # update(y_k) for each sample, in order
        estimate = calibrator.estimate
        return scale * estimate.A, estimate.b

    def run_two_step(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fit = twostep.two_step(y, noise_std=zhao.NOISE_SIGMA_G)
        return scale * fit.A, fit.b

    return {"ckf": run_ckf, "two-step": run_two_step}


RUNS = {
    "figure8": lambda p: run_figure8(int(p["seed"])),
    "comparison": lambda p: run_comparison(str(p["scenario"]), str(p["method"]), int(p["seed"])),
    "zhao-table1": lambda p: run_zhao(int(p["seed"]), bool(p["traces"])),
}


def run_task(task: Task) -> dict:
    """The run function of :func:`magcal_evaluation.study.runner.run_tasks` for this study's
    tasks."""
    return RUNS[task.experiment](task.params)


def describe_build() -> str:
    return f"magcal {__version__}"
