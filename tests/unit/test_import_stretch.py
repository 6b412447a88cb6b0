# SPDX-License-Identifier: Apache-2.0
"""The hand-rotation detector (magcal.logs.stretch) on synthetic inertial data."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.calib import frames
from magcal.logs.stretch import StretchConfig, explain_none, find_hand_rotation
from magcal.sim import trajectory

RATE_HZ = 50.0


def _segments(parts: list[tuple[str, float]], seed: int = 0):
    """Concatenate (kind, seconds) parts: "rest", "hand" (tumbling, hand accelerations),
    "yaw" (level yaw turns with 1.5 m/s² accelerations, like a flight), "fast-acc" (tumbling
    with 5 m/s² accelerations). Returns t, gyr, acc, and the (start, end) of each part."""
    rng = np.random.default_rng(seed)
    qs, spans = [], []
    t0 = 0.0
    for kind, seconds in parts:
        n = int(round(seconds * RATE_HZ))
        if kind == "rest":
            q = np.repeat(trajectory.random_rotation(rng)[None], n + 1, axis=0)
            acc_n = np.zeros((n, 3))
        else:
            motion, acc_rms, rate = {
                "hand": ("tumble", 0.3, 1.5),
                "yaw": ("yaw-only", 1.5, 0.6),
                "fast-acc": ("tumble", 5.0, 1.5),
            }[kind]
            tr = trajectory.make_trajectory(
                rng, RATE_HZ, 0.0, seconds + 1.0 / RATE_HZ, motion, rate, acc_rms_m_s2=acc_rms
            )
            q, acc_n = tr.q_nb[: n + 1], tr.acc_n[:n]
        gyr = trajectory.body_rates(q, RATE_HZ)
        R = frames.quat_to_matrix(q[:-1])
        acc = np.einsum("kji,kj->ki", R, acc_n - frames.gravity_n())
        qs.append((gyr, acc))
        spans.append((t0, t0 + (n - 1) / RATE_HZ))
        t0 += n / RATE_HZ
    gyr = np.concatenate([g for g, _ in qs])
    acc = np.concatenate([a for _, a in qs])
    t = np.arange(gyr.shape[0]) / RATE_HZ
    return t, gyr + rng.normal(0, 0.005, gyr.shape), acc + rng.normal(0, 0.02, acc.shape), spans


def _mask(t: np.ndarray, span: tuple[float, float]) -> np.ndarray:
    return (t >= span[0]) & (t <= span[1])


def test_finds_the_hand_rotation_and_skips_the_armed_flight():
    parts = [("rest", 5), ("hand", 30), ("rest", 5), ("yaw", 20), ("rest", 5)]
    t, gyr, acc, spans = _segments(parts)
    armed = _mask(t, spans[3])
    found = find_hand_rotation(t, gyr, acc, armed=armed)
    assert len(found) == 1
    s = found[0]
    # edges: the rotation ramps up from rest, and the 1 s moving average moves each edge
    assert abs(s.start_s - spans[1][0]) <= 1.0 and abs(s.end_s - spans[1][1]) <= 1.0
    assert s.tilt_coverage > 0.4
    # the margin takes in the rest around it: 2 s on each side
    assert s.from_s == pytest.approx(s.start_s - 2.0, abs=0.03)
    assert s.to_s == pytest.approx(s.end_s + 2.0, abs=0.03)


def test_without_armed_state_a_level_flight_is_no_hand_rotation():
    """Flight keeps gravity along the body's vertical: too little tilt coverage."""
    parts = [("rest", 5), ("yaw", 30), ("rest", 5), ("hand", 15), ("rest", 3)]
    t, gyr, acc, spans = _segments(parts)
    found = find_hand_rotation(t, gyr, acc)
    assert len(found) == 1
    assert abs(found[0].start_s - spans[3][0]) <= 1.0
    # with the tilt requirement off, the flight is a candidate, ranked below the hand rotation
    loose = find_hand_rotation(t, gyr, acc, config=StretchConfig(min_tilt_coverage=0.0))
    assert len(loose) == 2 and loose[0].start_s == found[0].start_s
    assert loose[1].tilt_coverage < 0.1


def test_throttle_and_unusable_samples_count_as_flight():
    t, gyr, acc, spans = _segments([("rest", 3), ("hand", 20), ("rest", 3)])
    hand = _mask(t, spans[1])
    assert find_hand_rotation(t, gyr, acc, throttle=np.where(hand, 0.4, 0.0)) == []
    assert find_hand_rotation(t, gyr, acc, unusable=hand) == []
    assert len(find_hand_rotation(t, gyr, acc, throttle=np.zeros(t.size))) == 1


def test_large_accelerations_are_not_a_hand():
    t, gyr, acc, spans = _segments([("rest", 3), ("fast-acc", 20), ("rest", 3)], seed=2)
    assert find_hand_rotation(t, gyr, acc) == []
    text = explain_none(t, gyr, acc)
    assert "accelerating" in text


def test_a_short_pause_joins_a_long_one_splits():
    parts = [("rest", 4), ("hand", 12), ("rest", 1.5), ("hand", 12), ("rest", 15)]
    parts += [("hand", 8), ("rest", 4)]
    t, gyr, acc, spans = _segments(parts, seed=3)
    found = find_hand_rotation(t, gyr, acc)
    assert len(found) == 2
    best = found[0]
    assert abs(best.start_s - spans[1][0]) <= 1.0 and abs(best.end_s - spans[3][1]) <= 1.0
    assert abs(found[1].start_s - spans[5][0]) <= 1.0


def test_an_armed_pause_does_not_join():
    parts = [("rest", 4), ("hand", 12), ("rest", 2), ("hand", 12), ("rest", 4)]
    t, gyr, acc, spans = _segments(parts, seed=4)
    armed = _mask(t, spans[2])
    found = find_hand_rotation(t, gyr, acc, armed=armed)
    assert len(found) == 2
    # the margin stops where the vehicle was armed
    first = min(found, key=lambda s: s.start_s)
    assert first.to_s < spans[2][0]


def test_more_coverage_wins_then_length():
    """A long level turn against a shorter tumble: the tumble covers more tilt."""
    parts = [("rest", 3), ("hand", 10), ("rest", 10), ("yaw", 40), ("rest", 3)]
    t, gyr, acc, spans = _segments(parts, seed=5)
    # without the coverage minimum both are candidates
    cfg = StretchConfig(min_tilt_coverage=0.0)
    found = find_hand_rotation(t, gyr, acc, config=cfg)
    assert found[0].duration_s < found[1].duration_s
    assert found[0].tilt_coverage > found[1].tilt_coverage + cfg.coverage_tie
    # two stretches of equal coverage: the longer wins
    tie = StretchConfig(min_tilt_coverage=0.0, coverage_tie=1.0)
    assert find_hand_rotation(t, gyr, acc, config=tie)[0].duration_s == max(
        s.duration_s for s in found
    )


def test_nothing_to_find():
    t, gyr, acc, _ = _segments([("rest", 20)])
    assert find_hand_rotation(t, gyr, acc) == []
    assert "for at most 0.0 s" in explain_none(t, gyr, acc)
    assert find_hand_rotation(t[:1], gyr[:1], acc[:1]) == []
    t, gyr, acc, _ = _segments([("rest", 3), ("hand", 3), ("rest", 3)])
    assert find_hand_rotation(t, gyr, acc) == []
    assert "needs 5 s" in explain_none(t, gyr, acc)
