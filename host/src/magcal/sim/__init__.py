# SPDX-License-Identifier: Apache-2.0
"""Simulated sessions with known truth: sensor models, trajectories, scenarios.

Start with :func:`simulate` and :func:`preset`; the pieces live in ``model`` (sensor
parameters, measurement model), ``trajectory`` (motion) and ``scenarios`` (configuration,
presets, truth files).
"""

from magcal.sim.model import (
    DIP_LINKOPING_DEG,
    SensorTruth,
    sample_handheld_magnet,
    sample_mems,
    sample_table2,
)
from magcal.sim.scenarios import (
    PRESETS,
    ScenarioConfig,
    SimTruth,
    TruthFormatError,
    preset,
    read_truth,
    simulate,
    truth_to_dict,
    write_truth,
)
from magcal.sim.trajectory import Trajectory, make_trajectory

__all__ = [
    "DIP_LINKOPING_DEG",
    "PRESETS",
    "ScenarioConfig",
    "SensorTruth",
    "SimTruth",
    "Trajectory",
    "TruthFormatError",
    "make_trajectory",
    "preset",
    "read_truth",
    "sample_handheld_magnet",
    "sample_mems",
    "sample_table2",
    "simulate",
    "truth_to_dict",
    "write_truth",
]
