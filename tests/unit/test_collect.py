# SPDX-License-Identifier: Apache-2.0
"""magcal.device.collect against a fake client: units and exact scales, metadata, the stop
conditions (samples, duration, coverage), dropped samples from seq gaps (with the uint32 wrap)
and the device's count, Ctrl-C and errors keeping what was collected, and the session file
reading back."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magcal.device import collect as col
from magcal.device.client import (
    Corrected,
    DeviceError,
    DeviceInfo,
    DeviceTimeoutError,
    ParamSet,
    ParamWhich,
    Sample,
    Scale,
    SensorInfo,
    StreamStats,
)
from magcal.device.framing import crc32_iso_hdlc
from magcal.device.generated import Status, Unit
from magcal.errors import MagcalError
from magcal.io.session import read_session, write_session
from magcal.sim.scenarios import preset, simulate

MAG = Scale(1, 6842, 0, Unit.GAUSS)  # 1e-4 / 6842 T = 0.0146156 uT per count
ACC = Scale(122, 1, -6, Unit.STANDARD_GRAVITY)
GYR = Scale(70, 1, -3, Unit.DEG_PER_S)
FIELD_UT = 50.0


def _info() -> DeviceInfo:
    fs = Scale(4, 1, 0, Unit.GAUSS)
    return DeviceInfo(
        fw_version=(1, 2, 3),
        fw_build=0xABCDEF01,
        protocol_version=1,
        params_format_version=1,
        params_size=52,
        device_uid=(1, 2, 3),
        sample_rate_mhz=100_000,
        sensors=(
            SensorInfo("mag", 0x3D, "LIS3MDL", fs, MAG),
            SensorInfo("acc", 0x6C, "LSM6DSO", fs, ACC),
            SensorInfo("gyr", 0x6C, "LSM6DSO", fs, GYR),
        ),
    )


def _counts(x: np.ndarray, scale: Scale, unit_si: float) -> np.ndarray:
    return np.clip(np.rint(x * unit_si / scale.si), -32768, 32767).astype(int)


def _samples(n=None, motion="tumble", seed=3, first_seq=100, duration_s=120.0, rate=2.0):
    session, _ = simulate(
        preset("mems", duration_s=duration_s, motion=motion, max_rate_rad_s=rate), seed=seed
    )
    k = len(session) if n is None else n
    mag = _counts(session.mag[:k] * FIELD_UT, MAG, 1e-6)
    acc = _counts(session.acc[:k], ACC, 1.0)
    gyr = _counts(session.gyr[:k], GYR, 1.0)
    return [
        Sample(
            (first_seq + i) % (1 << 32),
            5_000_000 + 10_000 * i,
            tuple(mag[i]),
            tuple(acc[i]),
            tuple(gyr[i]),
        )
        for i in range(k)
    ]


class FakeClient:
    """The part of DeviceClient that collect uses; a fake clock advancing 10 ms a sample."""

    url = "socket://fake:1"
    version = 1

    def __init__(
        self, samples, *, interrupt_at=None, error_at=None, dropped=0, stop_error=None, late=0
    ):
        """late : samples that arrive while stream_stop waits for its response (queued, read
        after it returns or raises)."""
        self.samples = list(samples)
        self.late = late
        self.queued: list[Sample] = []
        self.i = 0
        self.now = 0.0
        self.interrupt_at = interrupt_at
        self.error_at = error_at
        self.dropped = dropped
        self.stop_error = stop_error
        self.calls: list[str] = []

    def clock(self) -> float:
        return self.now

    def stream_start(self, kind=0, decimation=1, count=0):
        self.calls.append("start")

    def stream_stop(self):
        self.calls.append("stop")
        self.queued = self.samples[self.i : self.i + self.late]
        self.i += len(self.queued)
        if self.stop_error:
            raise self.stop_error
        return StreamStats(self.i, self.dropped)

    def read_stream(self, timeout_s=2.0):
        if self.interrupt_at is not None and self.i == self.interrupt_at:
            self.interrupt_at = None
            raise KeyboardInterrupt
        if self.error_at is not None and self.i == self.error_at:
            self.error_at = None
            raise DeviceError("stream on fake: link lost", Status.E_STATE, "stream")
        if self.queued:
            return self.queued.pop(0)
        if self.i >= len(self.samples) or "stop" in self.calls:
            self.now += timeout_s
            raise DeviceTimeoutError("no sample", Status.E_EMPTY, "stream")
        self.now += 0.01
        s = self.samples[self.i]
        self.i += 1
        return s


def _collect(client, **kw):
    return col.collect(client, _info(), clock=client.clock, **kw)


def test_units_scales_and_metadata(tmp_path):
    samples = _samples(300)
    client = FakeClient(samples)
    r = _collect(client, max_samples=300)
    assert r.stopped == "samples" and r.samples == 300 and client.calls == ["start", "stop"]
    s = r.session
    assert len(s) == 300
    # t: device seconds; mag: uT from the exact rational; acc m/s^2; gyr rad/s.
    assert s.t[0] == 5.0 and np.allclose(np.diff(s.t), 0.01)
    mag_counts = np.array([x.mag for x in samples])
    assert s.mag[0, 0] == float(mag_counts[0, 0] * 100 / 6842)  # exact, rounded once
    assert np.allclose(np.linalg.norm(s.acc[:50], axis=1), 9.81, atol=0.2)  # at rest first
    acc_counts = np.array([x.acc for x in samples])
    assert np.array_equal(s.acc, ACC.counts_to_si(acc_counts))
    gyr_counts = np.array([x.gyr for x in samples])
    assert np.allclose(s.gyr, gyr_counts * 0.07 * math.pi / 180, rtol=1e-15)
    m = s.meta
    assert m["mag_unit"] == "uT" and m["device_uid"] == "000000010000000200000003"
    assert m["firmware"] == "1.2.3" and m["firmware_build"] == "abcdef01"
    assert m["protocol_version"] == "1" and m["port"] == "socket://fake:1"
    assert m["mag_count_scale"].startswith("1/6842e0 gauss = ")
    assert m["acc_count_scale"].startswith("122/1e-6 standard_gravity")
    assert m["mag_sensor"] == "LIS3MDL (id 0x3d)"
    assert m["samples"] == "300" and m["dropped"] == "0" and m["stopped"] == "samples"
    assert "uid 000000010000000200000003" in m["source"] and "1.2.3" in m["source"]
    # Writes and reads back bit-exact with its metadata.
    write_session(tmp_path / "s.csv", s)
    back = read_session(tmp_path / "s.csv")
    assert np.array_equal(back.mag, s.mag) and back.meta == s.meta


def test_duration_stops_on_the_host_clock():
    client = FakeClient(_samples(1000))
    r = _collect(client, duration_s=3.0)
    assert r.stopped == "duration" and 295 <= r.samples <= 301


def test_coverage_target_stops_a_tumbling_session_but_not_before_min_samples():
    progress = []
    client = FakeClient(_samples())
    r = _collect(client, coverage_target=0.9, min_samples=500, progress=progress.append)
    assert r.stopped == "coverage" and r.coverage.coverage >= 0.9
    assert r.samples >= 500 and r.samples < len(client.samples)
    assert progress and progress[-1].samples == r.samples
    assert progress[-1].coverage >= 0.9 and progress[-1].rate_hz == pytest.approx(100, rel=0.05)
    assert float(r.session.meta["coverage"].split()[0]) >= 90.0


def test_yaw_only_does_not_reach_the_target_and_hints_at_z():
    client = FakeClient(_samples(3000, motion="yaw-only", duration_s=40.0))
    r = _collect(client, coverage_target=0.9, max_samples=3000)
    assert r.stopped == "samples" and r.coverage.coverage < 0.4
    assert "z axis" in r.coverage.hint


def test_seq_gaps_across_the_uint32_wrap_and_the_device_count():
    samples = _samples(200, first_seq=(1 << 32) - 50)
    kept = samples[:40] + samples[45:60] + samples[70:]  # gaps of 5 (before the wrap) and 10
    r = _collect(FakeClient(kept), max_samples=len(kept))
    assert r.gaps == 15 and r.dropped == 15 and r.session.meta["seq_gaps"] == "15"
    # Drops after the last sample received show only in the device's count.
    r = _collect(FakeClient(kept, dropped=20), max_samples=len(kept))
    assert r.gaps == 15 and r.device_dropped == 20 and r.dropped == 20
    assert r.session.meta["device_dropped"] == "20" and r.session.meta["dropped"] == "20"


def test_ctrl_c_stops_the_stream_and_keeps_the_samples():
    client = FakeClient(_samples(500), interrupt_at=123)
    r = _collect(client, duration_s=100.0)
    assert r.interrupted and r.samples == 123 and client.calls == ["start", "stop"]
    assert len(r.session) == 123 and r.session.meta["stopped"] == "interrupted"


def test_an_error_raises_with_the_partial_result():
    client = FakeClient(_samples(500), error_at=77)
    with pytest.raises(
        col.CollectError, match="after 77 samples: stream on fake: link lost"
    ) as info:
        _collect(client, duration_s=100.0)
    assert info.value.result.samples == 77 and info.value.result.stopped == "error"
    assert len(info.value.result.session) == 77 and client.calls == ["start", "stop"]


def test_a_stall_is_an_error_and_a_failed_stop_is_unknown_drops():
    client = FakeClient(
        _samples(50), stop_error=DeviceTimeoutError("gone", Status.E_EMPTY, "stream_stop")
    )
    with pytest.raises(col.CollectError, match="no sample for 5 s") as info:
        _collect(client, duration_s=100.0)
    assert info.value.result.samples == 50
    assert info.value.result.session.meta["device_dropped"] == "unknown"


def test_samples_arriving_during_the_stop_do_not_overshoot_max_samples():
    client = FakeClient(_samples(300), late=5)
    r = _collect(client, max_samples=100)
    assert r.stopped == "samples" and r.samples == 100 and len(r.session) == 100
    assert r.session.meta["samples"] == "100" and client.calls == ["start", "stop"]
    assert not client.queued  # the rest were read (not left for the client's next user)


def test_samples_arriving_during_the_stop_are_kept():
    client = FakeClient(_samples(300), late=5)
    r = _collect(client, duration_s=1.0)
    assert r.stopped == "duration" and r.samples == client.i
    assert r.session.t[-1] == client.samples[client.i - 1].t_us / 1e6


def test_a_failed_stop_still_keeps_the_queued_samples(caplog):
    client = FakeClient(
        _samples(300),
        late=5,
        stop_error=DeviceTimeoutError("no response", Status.E_EMPTY, "stream_stop"),
    )
    r = _collect(client, duration_s=1.0)
    assert r.stopped == "duration" and r.device_dropped == -1
    assert r.samples == client.i and len(r.session) == client.i  # the 5 late ones too
    assert r.session.meta["device_dropped"] == "unknown"
    assert "could not stop the stream (no response)" in caplog.text


def test_no_samples_gives_no_session():
    with pytest.raises(col.CollectError) as info:
        _collect(FakeClient([]), duration_s=100.0)
    assert info.value.result.session is None and info.value.result.samples == 0


def test_time_not_increasing_is_skipped_and_counted():
    samples = _samples(100)
    samples[50] = Sample(
        samples[50].seq, samples[49].t_us, *[getattr(samples[50], k) for k in ("mag", "acc", "gyr")]
    )
    r = _collect(FakeClient(samples), max_samples=99)
    assert r.out_of_order == 1 and len(r.session) == 99
    assert r.session.meta["out_of_order_skipped"] == "1"


def test_a_stop_condition_is_required():
    with pytest.raises(MagcalError, match="give a stop condition"):
        _collect(FakeClient([]))


# ----------------------------------------------------------------------------- verify
# (magcal.device.verify's measures, on the same simulated data: kept here with collect's
# fake client.)


def test_verify_measures_tell_a_right_calibration_from_a_wrong_one():
    from magcal.device.verify import heading_consistency, norm_spread

    session, truth = simulate(preset("mems", duration_s=20.0), seed=3)
    d, o = truth.sensor.D, truth.sensor.o
    right = np.linalg.solve(d, (session.mag - o).T).T
    wrong = np.linalg.solve(d, (session.mag - o - np.array([0.1, 0, 0])).T).T
    assert norm_spread(right).rel_std < 0.01 < norm_spread(wrong).rel_std
    good = heading_consistency(session.t, session.acc, session.gyr, right)
    bad = heading_consistency(session.t, session.acc, session.gyr, wrong)
    assert good.rms_deg < 2.0 and bad.rms_deg > 2.0 and bad.dip_std_deg > 5 * good.dip_std_deg
    assert abs(good.dip_mean_deg - truth.scenario.dip_deg) < 0.5
    # The rest at the start gives the gyroscope bias.
    assert np.allclose(good.gyro_bias, truth.sensor.gyro_bias, atol=0.003)


def test_verify_refuses_a_device_without_parameters():
    from magcal.device.verify import VerifyError, verify

    class NoParams(FakeClient):
        def param_get(self, which=0):
            raise DeviceError("param_get(active): E_NO_PARAMS", Status.E_NO_PARAMS, "param_get")

    with pytest.raises(VerifyError, match=r"no active parameter set \(E_NO_PARAMS\).*magcal flash"):
        verify(NoParams([]), _info())


class VerifyClient:
    """The part of DeviceClient that verify uses: an identity parameter set and a corrected
    stream of the given seqs (the device's output for each raw sample)."""

    url = "socket://fake:1"

    def __init__(self, seqs, *, read_error=None, stop_error=None):
        from magcal.device import fixed_point

        self.params = fixed_point.from_calibration(np.eye(3), np.zeros(3))
        self.blob = fixed_point.encode(self.params)
        raw = np.array([x.mag for x in _samples(len(seqs))], dtype=np.int64)
        out = fixed_point.emulate(self.params, raw)
        self.msgs = [
            Corrected(q, 5_000_000 + 10_000 * i, tuple(raw[i]), self.params.out_exp, tuple(out[i]))
            for i, q in enumerate(seqs)
        ]
        self.read_error = read_error
        self.stop_error = stop_error
        self.calls: list[str] = []

    def param_get(self, which=0):
        return ParamSet(ParamWhich.ACTIVE, 1, crc32_iso_hdlc(self.blob), self.blob)

    def stream_start(self, kind=0, decimation=1, count=0):
        self.calls.append("start")

    def stream_stop(self):
        self.calls.append("stop")
        if self.stop_error:
            raise self.stop_error
        return StreamStats(len(self.msgs), 0)

    def read_stream(self, timeout_s=2.0):
        if not self.msgs:
            raise self.read_error or DeviceTimeoutError("no sample", Status.E_EMPTY, "stream")
        return self.msgs.pop(0)


def test_verify_counts_a_repeated_seq_as_no_gap():
    from magcal.device.verify import verify

    # A duplicate (no gap, not 2^32 - 1), the uint32 wrap (no gap), then 2 missing.
    seqs = [(1 << 32) - 2, (1 << 32) - 1, (1 << 32) - 1, 0, 3, 4]
    r = verify(VerifyClient(seqs), _info(), n_samples=len(seqs), heading=False)
    assert r.dropped == 2 and r.mismatches == 0 and r.norm.n == len(seqs)


def test_seq_gap():
    assert [col.seq_gap(5, q) for q in (6, 8, 5, 4, 3)] == [0, 2, 0, 0, 0]
    assert col.seq_gap((1 << 32) - 1, 0) == 0 and col.seq_gap((1 << 32) - 2, 1) == 2


def test_verify_a_failed_stop_is_raised_when_nothing_else_is():
    from magcal.device.verify import verify

    stop_error = DeviceTimeoutError("stream_stop: no response", Status.E_EMPTY, "stream_stop")
    client = VerifyClient(range(5), stop_error=stop_error)
    with pytest.raises(DeviceTimeoutError, match="stream_stop: no response"):
        verify(client, _info(), n_samples=5, heading=False)


def test_verify_a_failed_stop_after_a_read_error_is_logged_and_the_read_error_raised(caplog):
    from magcal.device.verify import verify

    read_error = DeviceTimeoutError("stream on fake: no sample", Status.E_EMPTY, "stream")
    stop_error = DeviceError("stream_stop: link lost", Status.E_STATE, "stream_stop")
    client = VerifyClient(range(3), read_error=read_error, stop_error=stop_error)
    with pytest.raises(DeviceTimeoutError, match="no sample"):
        verify(client, _info(), n_samples=5, heading=False)
    assert client.calls == ["start", "stop"]
    assert "could not stop the stream after DeviceTimeoutError (stream_stop: link lost)" in (
        caplog.text
    )


@pytest.mark.parametrize(
    "unit, factor, match",
    [
        ("T", 1.0, r"mag_unit is 'T'; .* in uT recorded with magcal collect"),
        ("uT", 1.001, "not whole counts of this device's magnetometer"),
    ],
)
def test_verify_refuses_an_unusable_session_before_streaming(unit, factor, match):
    from magcal.device.verify import VerifyError, verify
    from magcal.io.session import session_from_arrays

    s = _collect(FakeClient(_samples(100)), max_samples=100).session
    bad = session_from_arrays(s.t, s.gyr, s.acc, s.mag * factor, {**s.meta, "mag_unit": unit})
    client = VerifyClient(range(5))
    with pytest.raises(VerifyError, match=match):
        verify(client, _info(), n_samples=5, session=bad)
    assert client.calls == []  # nothing streamed


def test_verify_measures_a_session_from_collect():
    from magcal.device.verify import verify

    s = _collect(FakeClient(_samples(1000)), max_samples=1000).session
    r = verify(VerifyClient(range(5)), _info(), n_samples=5, heading=False, session=s)
    assert r.session_heading is not None and r.session_heading.n > 900


# ---------------------------------------------------------------- the command's handling
# (commands/collect.py, shared by the serial and the MAVLink paths)


class _Progress:
    def __init__(self):
        self.done_calls = 0

    def __call__(self, p):
        pass

    def done(self):
        self.done_calls += 1


def test_command_keeps_the_samples_of_a_collection_that_failed(tmp_path):
    from magcal.commands.collect import collect_saving_partial

    client = FakeClient(_samples(500), error_at=77)
    path = tmp_path / "s.csv"
    progress = _Progress()
    with pytest.raises(MagcalError, match=f"the 77 samples collected were written to {path}"):
        collect_saving_partial(lambda: _collect(client, duration_s=100.0), str(path), progress)
    assert len(read_session(path)) == 77 and progress.done_calls >= 1


def test_command_writes_nothing_when_a_failed_collection_received_nothing(tmp_path):
    from magcal.commands.collect import collect_saving_partial

    client = FakeClient(_samples(500), error_at=0)
    path = tmp_path / "s.csv"
    with pytest.raises(MagcalError, match="no samples were received, nothing written"):
        collect_saving_partial(lambda: _collect(client, duration_s=100.0), str(path), _Progress())
    assert not path.exists()


def test_command_exit_codes_after_a_collection(tmp_path, capsys):
    import argparse

    from magcal.cli import EXIT_INTERRUPTED
    from magcal.commands.collect import finish_collect

    path = tmp_path / "s.csv"
    args = argparse.Namespace(output=str(path), coverage=None)
    interrupted = _collect(FakeClient(_samples(500), interrupt_at=123), duration_s=100.0)
    assert finish_collect(args, interrupted, 100, "on fake", "check it", None) == EXIT_INTERRUPTED
    assert len(read_session(path)) == 123
    assert "interrupted; the partial session is in" in capsys.readouterr().err
    # Interrupted, a short session is kept without complaint; stopped otherwise, it is an error.
    assert finish_collect(args, interrupted, 200, "on fake", "check it", None) == EXIT_INTERRUPTED
    short = dataclasses.replace(interrupted, stopped="duration")
    with pytest.raises(MagcalError, match="has 123 samples; calibration needs at least 200"):
        finish_collect(args, short, 200, "on fake", "check it", None)
    assert finish_collect(args, short, 100, "on fake", "check it", None) == 0
    empty = col.CollectResult(None, 0, "duration", 0, 0, 0, 0, interrupted.coverage, 1.0)
    path.unlink()
    with pytest.raises(MagcalError, match="collect on fake: no samples were received.*; check it"):
        finish_collect(args, empty, 100, "on fake", "check it", None)
    assert not path.exists()
