# SPDX-License-Identifier: Apache-2.0
"""``magcal import`` of a flight: the armed, airborne stretch with GNSS, every compass, GNSS
velocity, current and throttle (magcal.logs.flight).

The ArduPilot flights of ``../shared/flightlogs`` (beside the checkout; the tests that need
them are skipped with a message where it is absent) carry their truth: the simulated sensor
of each compass, against which the undone fields are checked. The decimation and the
refusals are also checked on synthetic streams, which need no shared data.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from magcal.cli import main
from magcal.io.session import read_session, write_session
from magcal.logs import LogImportError, dataflash, import_log, read_log
from magcal.logs.flight import MAX_IMU_ROW_HZ, find_flight, flight_arrays
from magcal.logs.streams import (
    GnssStream,
    ImuStream,
    LogStreams,
    MagStream,
    ParamTimeline,
    StepSignal,
)

REPO_ROOT = Path(__file__).resolve().parents[2]
#: ArduPilot flights with a known compass error: ``shared/flightlogs`` beside the checkout.
FLIGHTS = REPO_ROOT.parent / "shared" / "flightlogs"
NAMES = ("f1_plain", "f2_motor", "f3_misaligned")
#: The flights' Earth field (README there): strength, inclination and declination.
FIELD_MG, INCLINATION_DEG, DECLINATION_DEG = 579.0, -65.8, 12.8
#: Compasses 2 and 3: SITL's default error, offsets only (README there).
SITL_DEFAULT_OFS = np.array([5.0, 13.0, -18.0])

needs_flights = pytest.mark.skipif(
    not all((FLIGHTS / f"{n}.bin").is_file() for n in NAMES),
    reason=f"the shared flight logs are not at {FLIGHTS} (the synthetic tests still run)",
)


@pytest.fixture(scope="module")
def flights():
    return {n: import_log(str(FLIGHTS / f"{n}.bin")) for n in NAMES}


def _field(session, compass: int) -> np.ndarray:
    if compass == 1:
        return session.mag
    return np.column_stack([session.extra[f"mag{compass}_{a}"] for a in "xyz"])


@needs_flights
@pytest.mark.parametrize("name", NAMES)
def test_a_flight_imports_as_a_flight_session_with_three_compasses(flights, name):
    result = flights[name]
    s = result.session
    assert result.stretch is None and result.flight is not None
    assert result.flight.airborne_by == "the land detector"
    meta = s.meta
    assert meta["motion"] == "flight"
    assert meta["compasses"] == "1,2,3"
    assert 330.0 < float(meta["flight_airborne_s"]) < 350.0  # 339 s airborne (README)
    lat, lon, alt_km = (float(v) for v in meta["location"].split(","))
    assert abs(lat + 35.3633) < 0.01 and abs(lon - 149.1652) < 0.01 and 0.58 < alt_km < 0.66
    assert re.fullmatch(r"\d{4}-\d\d-\d\d", meta["date"])
    for key in ("source", "mag_unit", "mag_frame", "log_start_s", "log_end_s", "resampling"):
        assert key in meta
    # the parameters in force of every compass, their motor compensation and its type
    for n in ("COMPASS_OFS_X", "COMPASS_DIA2_Y", "COMPASS_ODI3_Z", "COMPASS_MOT2_X"):
        assert f"param.{n}" in meta
    for n in ("COMPASS_MOT3_Z", "COMPASS_ORIENT3", "COMPASS_SCALE2", "COMPASS_MOTCT"):
        assert f"param.{n}" in meta
    assert float(meta["param.COMPASS_OFS2_Y"]) == 13.0
    expected = [f"mag{c}_{a}" for c in (2, 3) for a in "xyz"]
    assert list(s.extra) == expected + ["vel_n", "vel_e", "vel_d", "current", "throttle"]
    for c in (1, 2, 3):
        field = _field(s, c)
        has = ~np.isnan(field[:, 0])
        assert 3300 < has.sum() < 3600  # 10 Hz over 344 s
        assert np.isnan(field[~has]).all()
    # ArduPilot stamps every MAG instance at one TimeUS: they share rows
    assert np.array_equal(~np.isnan(s.mag[:, 0]), ~np.isnan(s.extra["mag2_x"]))
    vel = np.column_stack([s.extra[f"vel_{a}"] for a in "ned"])
    has_vel = ~np.isnan(vel[:, 0])
    assert 1600 < has_vel.sum() < 1800  # GNSS at 5 Hz
    assert np.nanmax(np.linalg.norm(vel[:, :2], axis=1)) > 10.0  # fast legs at 12 m/s
    assert np.nanmin(vel[:, 2]) < -1.0 and np.nanmax(vel[:, 2]) > 1.0  # climbs and descents
    assert 20.0 < np.nanmedian(s.extra["current"]) < 40.0  # 23–35 A
    throttle = s.extra["throttle"]
    assert np.nanmin(throttle) >= 0.0 and 0.2 < np.nanmedian(throttle) < 0.8
    # the IMU at its own 25 Hz, no decimation
    assert "a row at each IMU sample (25.0 Hz)" in meta["resampling"]
    assert 8500 < (~np.isnan(s.acc[:, 0])).sum() < 8700


@needs_flights
@pytest.mark.parametrize("name", NAMES)
def test_every_compass_is_the_simulated_sensor_with_the_correction_undone(flights, name):
    """The README's sensor model, with the true attitude (SIM), fits each compass's undone
    field to the log's resolution (1 mG, noise 5 mG over ten readings per sample) with the
    Earth field the README gives."""
    from scipy.spatial.transform import Rotation

    truth = json.loads((FLIGHTS / f"{name}.truth.json").read_text())
    result = flights[name]
    s = result.session
    df, _ = dataflash._open(str(FLIGHTS / f"{name}.bin"), None)
    try:
        sim = dataflash._decode(df, "SIM")
    finally:
        df.close()
    t_sim = sim["TimeUS"] * 1e-6
    sm = truth["sim"]
    for compass in (1, 2, 3):
        y = _field(s, compass)
        # a few hundred samples while turning slowly (each is a mean over 0.1 s)
        ok = ~np.isnan(y[:, 0]) & (np.linalg.norm(s.gyr, axis=1) < 0.05)
        t, y = s.t[ok], y[ok]
        k = np.clip(np.searchsorted(t_sim, t), 0, t_sim.size - 1)
        euler = np.column_stack([sim["Yaw"][k], sim["Pitch"][k], sim["Roll"][k]])
        R = Rotation.from_euler("ZYX", euler, degrees=True).as_matrix()
        if compass == 1:
            d, od = sm["DIA"], sm["ODI"]
            M = np.array([[d[0], od[0], od[1]], [od[0], d[1], od[2]], [od[1], od[2], d[2]]])
            ofs = np.array(sm["OFS"])
            rot = np.eye(3)
            if sm["ROT"] is not None:
                rot = Rotation.from_euler("ZYX", sm["ROT"][::-1], degrees=True).as_matrix()
        else:
            M, ofs, rot = np.eye(3), SITL_DEFAULT_OFS, np.eye(3)
        M_inv = np.linalg.inv(M)
        motor = np.outer(result.streams.current.at(t), sm["MOT"])
        # y = rotᵀ (M⁻¹ (Rᵀ B + MOT·I) − OFS)  ⇔  rot y + OFS − M⁻¹ MOT·I = M⁻¹ Rᵀ B
        lhs = y @ rot.T + ofs - motor @ M_inv.T
        A = np.einsum("ij,nkj->nik", M_inv, R)
        B = np.linalg.lstsq(A.reshape(-1, 3), lhs.reshape(-1), rcond=None)[0]
        residual = lhs - A @ B
        assert ok.sum() > 1000
        assert np.sqrt(np.mean(residual**2)) < 1.5, (name, compass)
        assert np.abs(residual).max() < 15.0, (name, compass)
        assert abs(np.linalg.norm(B) - FIELD_MG) < 3.0
        assert abs(np.degrees(np.arcsin(B[2] / np.linalg.norm(B))) - INCLINATION_DEG) < 0.3
        assert abs(np.degrees(np.arctan2(B[1], B[0])) - DECLINATION_DEG) < 0.3


@needs_flights
def test_the_session_is_written_and_read_back_exactly(flights, tmp_path):
    s = flights["f2_motor"].session
    path = tmp_path / "flight.csv"
    write_session(path, s)
    text = path.read_text()
    assert text.startswith("# magcal-session: 2\n")
    back = read_session(path, extra=True)
    assert list(back.extra) == list(s.extra)
    for name, column in s.extra.items():
        assert np.array_equal(back.extra[name], column, equal_nan=True), name
    assert np.array_equal(back.mag, s.mag, equal_nan=True)
    assert back.meta == s.meta
    plain = read_session(path)  # a reader that does not know the columns ignores them
    assert plain.extra == {} and np.array_equal(plain.t, s.t)


@needs_flights
def test_the_command_says_it_imported_the_flight(capfd, tmp_path):
    out = tmp_path / "s.csv"
    assert main(["import", str(FLIGHTS / "f1_plain.bin"), "-o", str(out)]) == 0
    text = "".join(capfd.readouterr())
    assert "no hand rotation; found a flight of 344" in text
    assert "every compass (1,2,3), GNSS velocity, battery current and throttle" in text
    assert "# motion: flight" in out.read_text()


@needs_flights
def test_start_and_end_still_choose_the_range(capfd, tmp_path):
    out = tmp_path / "s.csv"
    argv = ["import", str(FLIGHTS / "f1_plain.bin"), "--start", "100", "--end", "160"]
    assert main([*argv, "-o", str(out)]) == 0
    s = read_session(out, extra=True)
    assert 100.0 <= s.t[0] < 100.2 and 159.8 < s.t[-1] <= 160.0
    assert s.meta["motion"] == "flight" and "mag3_x" in s.extra
    # the ground before take-off: the hand-rotation session of today, without flight columns
    assert main([*argv[:2], "--start", "30", "--end", "55", "-o", str(out)]) == 0
    s = read_session(out, extra=True)
    assert "motion" not in s.meta and s.extra == {}


@needs_flights
def test_a_log_cut_to_its_ground_part_is_refused_naming_it(tmp_path, capfd):
    """The first 50 s of a flight log (on the ground, before take-off), cut at a message
    boundary: the land detector never spoke and GNSS height never rose."""
    path = FLIGHTS / "f1_plain.bin"
    df, _ = dataflash._open(str(path), None)
    try:
        imu = dataflash._decode(df, "IMU")
    finally:
        df.close()
    cut_at = int(imu["OFFSET"][np.searchsorted(imu["TimeUS"] * 1e-6, 50.0)])
    ground = tmp_path / "ground.bin"
    ground.write_bytes(path.read_bytes()[:cut_at])
    with pytest.raises(LogImportError, match="never left the ground"):
        import_log(str(ground))
    assert main(["import", str(ground), "-o", str(tmp_path / "s.csv")]) == 2
    err = capfd.readouterr().err
    refusal = [line for line in err.splitlines() if line.startswith("magcal import:")]
    assert len(refusal) == 1 and "Traceback" not in err
    assert refusal[0].startswith("magcal import: ground.bin: no stretch where the vehicle was")
    assert "no flight to import: the vehicle never left the ground" in refusal[0]


@needs_flights
def test_a_flight_without_gnss_is_refused_saying_so():
    streams = read_log(str(FLIGHTS / "f1_plain.bin"))
    flight, missing = find_flight(dataclasses.replace(streams, gnss=None))
    assert flight is None and "no GNSS" in missing
    g = streams.gnss
    no_fix = dataclasses.replace(g, fix=np.minimum(g.fix, 2))
    flight, missing = find_flight(dataclasses.replace(streams, gnss=no_fix))
    assert flight is None and "3D fix" in missing
    grounded = StepSignal(np.array([0.0]), np.array([0.0]), before=0.0)
    flight, missing = find_flight(dataclasses.replace(streams, airborne=grounded))
    assert flight is None and "never left the ground" in missing


# ------------------------------------------------------------------ synthetic streams
def _synthetic(imu_hz: float, seconds: float = 30.0, seed: int = 3) -> LogStreams:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / imu_hz) + 100.0
    gyr = np.column_stack([np.sin(t * w) for w in (1.3, 2.1, 0.7)]) + rng.normal(
        0, 0.01, (t.size, 3)
    )
    acc = rng.normal((0, 0, 9.81), 0.3, (t.size, 3))
    tm = np.arange(100.013, 100.0 + seconds - 0.1, 0.05)
    mags = [
        MagStream(tm, rng.normal(0, 300, (tm.size, 3)), k, "mG", "frame", f"MAG[{k - 1}]")
        for k in (1, 2)
    ]
    tg = np.arange(100.0, 100.0 + seconds, 0.2) + 0.0031
    n = tg.size
    gnss = GnssStream(
        tg,
        np.full(n, 3),
        np.full(n, 47.0),
        np.full(n, 8.0),
        np.linspace(500, 560, n),
        rng.normal(0, 3, (n, 3)),
        np.full(n, 1.7e9),
        "GPS",
    )
    return LogStreams(
        path="synthetic.bin",
        log_format="DataFlash",
        autopilot="ardupilot",
        imu=ImuStream(t, gyr, acc, 1, "IMU[0]"),
        mag=mags[0],
        params=ParamTimeline({}),
        other_mags=(mags[1],),
        gnss=gnss,
        current=StepSignal(np.array([105.0, 110.0]), np.array([20.0, 30.0])),
        throttle=StepSignal(np.array([101.0]), np.array([0.5])),
    )


def test_a_fast_imu_is_decimated_preserving_the_rotation():
    streams = _synthetic(imu_hz=400.0)
    a = flight_arrays(streams, 100.5, 125.0)
    assert a.decimation == 4
    imu_rows = ~np.isnan(a.acc[:, 0])
    assert 1.0 / np.median(np.diff(a.t[imu_rows])) <= MAX_IMU_ROW_HZ + 1e-6
    # the rows turn through the integral of the IMU's piecewise-linear rate (trapezoids)
    imu = streams.imu
    inside = (imu.t >= a.t[0]) & (imu.t <= a.t[-1])
    ti, gi = imu.t[inside], imu.gyr[inside]
    exact = np.sum(0.5 * (gi[1:] + gi[:-1]) * np.diff(ti)[:, None], axis=0)
    rows = np.sum(a.gyr[:-1] * np.diff(a.t)[:, None], axis=0)
    assert np.allclose(rows, exact, rtol=0, atol=1e-12)
    # the accelerometer of a row is the mean of its four samples
    first = int(np.flatnonzero(imu.t >= 100.5)[0])
    assert np.allclose(a.acc[imu_rows][0], imu.acc[first : first + 4].mean(axis=0))
    # magnetometers never interpolated: each sample on a row of its own time
    for k, m in ((1, streams.mag), (2, streams.other_mags[0])):
        has = ~np.isnan(a.mags[k][:, 0])
        sel = (m.t >= 100.5) & (m.t <= 125.0)
        assert np.array_equal(a.t[has], m.t[sel]) and np.array_equal(a.mags[k][has], m.mag[sel])
    # GNSS on the nearest row within half a row period (5 ms here), all of them
    has_vel = ~np.isnan(a.vel[:, 0])
    g = streams.gnss
    sel = (g.t >= 100.5) & (g.t <= 125.0)
    assert has_vel.sum() == sel.sum()
    assert np.all(np.abs(a.t[has_vel] - g.t[sel]) <= 0.005 + 1e-12)
    # current and throttle held, empty before their first sample
    assert np.isnan(a.current[a.t < 105.0]).all() and (a.current[a.t >= 110.0] == 30.0).all()
    assert np.isnan(a.throttle[a.t < 101.0]).all() and (a.throttle[a.t >= 101.0] == 0.5).all()


def test_an_imu_at_100_hz_or_below_keeps_every_sample():
    streams = _synthetic(imu_hz=100.0)
    a = flight_arrays(streams, 100.5, 125.0)
    assert a.decimation == 1
    imu = streams.imu
    inside = (imu.t >= 100.5) & (imu.t <= 125.0)
    assert np.array_equal(a.t[~np.isnan(a.acc[:, 0])], imu.t[inside])


def test_old_sessions_still_read(tmp_path):
    v1 = tmp_path / "v1.csv"
    v1.write_text(
        "# magcal-session: 1\nt,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,note\n"
        "0,0,0,0,0,0,9.8,1,2,3,7\n0.01,0,0,0,0,0,9.8,1,2,3,8\n"
    )
    s = read_session(v1, extra=True)
    assert list(s.extra) == ["note"] and s.extra["note"].tolist() == [7.0, 8.0]
    assert read_session(v1).extra == {}
    v2 = tmp_path / "v2.csv"
    v2.write_text(
        "# magcal-session: 2\nt,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z\n"
        "0,0,0,0,0,0,9.8,1,2,3\n0.01,0,0,0,,,,1,2,3\n"
    )
    s = read_session(v2, extra=True)
    assert s.extra == {} and np.isnan(s.acc[1]).all()
    bad = tmp_path / "bad.csv"
    bad.write_text(v1.read_text().replace(",8\n", ",x\n"))
    with pytest.raises(Exception, match="line 4: column note: 'x' is not a number"):
        read_session(bad, extra=True)
