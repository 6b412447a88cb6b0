# SPDX-License-Identifier: Apache-2.0
"""Result JSON files: the contract's keys, round trip, forward compatibility, error paths."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magcal.calib.frames import euler_zyx_to_matrix, field_direction
from magcal.errors import MagcalError, ResultFormatError
from magcal.io.result import (
    REQUIRED_KEYS,
    RESULT_FORMAT,
    CalibrationResult,
    ResultFileError,
    apply_correction,
    check_result_writable,
    read_result,
    result_from_dict,
    result_to_dict,
    write_result,
)

# The paper's Xsens estimate (Kok & Schön 2016, eq. 29).
D_PAPER = np.array([[0.74, -0.13, 0.01], [-0.12, 0.68, 0.01], [-0.03, 0.43, 1.00]])
O_PAPER = np.array([1.36, 1.22, -0.94])


def make_result(**changes) -> CalibrationResult:
    fields = {
        "method": "ml",
        "D": D_PAPER,
        "o": O_PAPER,
        "m_n": field_direction(np.deg2rad(70.0)),
        "dip_deg": 70.0,
        "gyro_bias": np.array([1e-3, -2e-3, 3e-4]),
        "warnings": ["little rotation about z"],
        "extra": {"Sigma_m": np.diag([1e-3, 2e-3, 3e-3]), "stats": {"cost": np.float64(12.5)}},
    }
    fields.update(changes)
    return CalibrationResult(**fields)


def written(tmp_path, data) -> str:
    path = tmp_path / "r.json"
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


# ---------------------------------------------------------------------------------------------
# The contract


def test_required_keys_are_the_contracts():
    # Pinned: docs/contracts.md, "Result file". Change only with the contract.
    assert REQUIRED_KEYS == (
        "format",
        "method",
        "D",
        "o",
        "D_inv",
        "m_n",
        "dip_deg",
        "gyro_bias",
        "warnings",
    )
    assert RESULT_FORMAT == "magcal-result/1"


def test_written_file_has_contract_layout(tmp_path):
    path = tmp_path / "r.json"
    write_result(path, make_result())
    data = json.loads(path.read_text())
    assert list(data)[: len(REQUIRED_KEYS)] == list(REQUIRED_KEYS)
    assert data["format"] == "magcal-result/1"
    assert data["D"] == D_PAPER.tolist()  # row-major list of lists
    assert data["D"][2] == [-0.03, 0.43, 1.0]
    np.testing.assert_allclose(np.array(data["D_inv"]) @ D_PAPER, np.eye(3), atol=1e-14)
    assert data["o"] == O_PAPER.tolist()
    assert data["gyro_bias"] == [1e-3, -2e-3, 3e-4]
    assert data["warnings"] == ["little rotation about z"]
    assert data["Sigma_m"][1] == [0.0, 2e-3, 0.0]
    assert data["stats"] == {"cost": 12.5}


def test_errors_are_magcal_errors():
    assert issubclass(ResultFormatError, MagcalError)


# ---------------------------------------------------------------------------------------------
# Round trip


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    D = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    # dip_deg = 1/3 and its m_n have no short decimal form: they must survive bit for bit.
    m_n = field_direction(np.deg2rad(1 / 3))
    r = make_result(D=D, o=rng.normal(size=3), m_n=m_n, dip_deg=1 / 3)
    path = tmp_path / "r.json"
    write_result(path, r)
    back = read_result(path)
    for name in ("D", "o", "m_n", "gyro_bias", "D_inv"):
        assert getattr(back, name).tobytes() == getattr(r, name).tobytes(), name
    assert back.dip_deg == 1 / 3
    assert back.method == "ml"
    assert back.warnings == r.warnings
    assert back.extra == r.extra
    assert result_to_dict(back) == result_to_dict(r)


def test_null_gyro_bias_round_trips(tmp_path):
    path = tmp_path / "r.json"
    write_result(path, make_result(method="init", gyro_bias=None, warnings=[]))
    assert json.loads(path.read_text())["gyro_bias"] is None
    back = read_result(path)
    assert back.gyro_bias is None
    assert back.warnings == []


def test_unknown_keys_are_kept(tmp_path):
    data = result_to_dict(make_result(extra={}))
    data["from_the_future"] = {"nested": [1, 2, {"x": None}]}
    back = read_result(written(tmp_path, data))
    assert back.extra == {"from_the_future": {"nested": [1, 2, {"x": None}]}}
    assert result_to_dict(back) == data


def test_extra_is_stored_json_ready():
    r = make_result()
    assert r.extra["Sigma_m"] == np.diag([1e-3, 2e-3, 3e-3]).tolist()
    assert type(r.extra["stats"]["cost"]) is float


def test_arrays_are_read_only_copies():
    D = D_PAPER.copy()
    r = make_result(D=D)
    D[0, 0] = 99.0
    assert r.D[0, 0] == 0.74
    with pytest.raises(ValueError):
        r.o[0] = 1.0


def test_D_inv_is_the_inverse():
    np.testing.assert_allclose(make_result().D_inv @ D_PAPER, np.eye(3), atol=1e-14)


# ---------------------------------------------------------------------------------------------
# apply_correction


def test_apply_correction_maps_ellipsoid_to_unit_sphere():
    rng = np.random.default_rng(2)
    r = make_result()
    m_b = rng.normal(size=(100, 3))
    m_b /= np.linalg.norm(m_b, axis=1, keepdims=True)
    y = m_b @ D_PAPER.T + O_PAPER  # the model y = D m_b + o, without noise
    np.testing.assert_allclose(apply_correction(r, y), m_b, atol=1e-12)


def test_apply_correction_keeps_rotation():
    R = euler_zyx_to_matrix(0.3, -0.2, 0.1)
    r = make_result(D=2.0 * R, o=np.zeros(3))
    y = np.array([[2.0, 0.0, 0.0]])
    np.testing.assert_allclose(apply_correction(r, y), (R.T @ [1.0, 0.0, 0.0])[None], atol=1e-15)


def test_apply_correction_single_sample_and_bad_shape():
    r = make_result()
    assert apply_correction(r, O_PAPER).shape == (3,)
    np.testing.assert_array_equal(apply_correction(r, O_PAPER), np.zeros(3))
    with pytest.raises(ValueError, match=r"mag must have shape \(N, 3\), got \(10, 2\)"):
        apply_correction(r, np.zeros((10, 2)))


# ---------------------------------------------------------------------------------------------
# Reading: error paths name the file and the key


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_missing_required_key(tmp_path, key):
    data = result_to_dict(make_result())
    del data[key]
    with pytest.raises(ResultFormatError, match=rf"r\.json: missing required key\(s\) {key};"):
        read_result(written(tmp_path, data))


def test_several_missing_keys_are_all_named(tmp_path):
    with pytest.raises(ResultFormatError, match="missing required key.* D, o, D_inv"):
        read_result(written(tmp_path, {"format": RESULT_FORMAT, "method": "ml"}))


def test_wrong_format(tmp_path):
    data = result_to_dict(make_result())
    data["format"] = "magcal-result/2"
    with pytest.raises(ResultFormatError, match=r"key 'format' is 'magcal-result/2'"):
        read_result(written(tmp_path, data))


def test_not_json(tmp_path):
    with pytest.raises(ResultFormatError, match=r"not valid JSON at line 2, column"):
        read_result(written(tmp_path, '{"format":\n ]'))


def test_not_an_object(tmp_path):
    with pytest.raises(ResultFormatError, match="expected a JSON object, got list"):
        read_result(written(tmp_path, [1, 2]))


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("D", [[1, 0, 0], [0, 1, 0]]),
        ("D", [1, 0, 0, 0, 1, 0, 0, 0, 1]),
        ("D_inv", [[1, 0, 0], [0, 1, 0], [0, 0]]),
        ("o", [0.0, 1.0]),
        ("m_n", [[1.0, 0.0, 0.0]]),
        ("gyro_bias", [0.0, 0.0, 0.0, 0.0]),
        ("o", "1,2,3"),
    ],
)
def test_wrong_shape_names_key(tmp_path, key, value):
    data = result_to_dict(make_result())
    data[key] = value
    with pytest.raises(ResultFormatError, match=rf"key '{key}' must be a 3"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize(("key", "value"), [("o", [0, "1", 0]), ("gyro_bias", [0, True, 0])])
def test_non_numbers_rejected(tmp_path, key, value):
    data = result_to_dict(make_result())
    data[key] = value
    with pytest.raises(ResultFormatError, match=rf"key '{key}' holds .*, not a number"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize("key", ["D", "o", "m_n", "gyro_bias"])
def test_non_finite_names_key(tmp_path, key):
    data = result_to_dict(make_result())
    value = np.array(data[key], dtype=float)
    value.flat[0] = np.nan
    data[key] = value.tolist()
    # Python's json writes and reads NaN (not standard JSON); the reader must still refuse it.
    with pytest.raises(ResultFormatError, match=rf"{key} has non-finite entries"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize("dip", [float("inf"), "70", None, True])
def test_bad_dip(tmp_path, dip):
    data = result_to_dict(make_result())
    data["dip_deg"] = dip
    with pytest.raises(ResultFormatError, match="key 'dip_deg' must be a finite number"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize("method", ["", 3, None])
def test_bad_method(tmp_path, method):
    data = result_to_dict(make_result())
    data["method"] = method
    with pytest.raises(ResultFormatError, match="key 'method' must be a non-empty string"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize("warnings", ["oops", [1], None])
def test_bad_warnings(tmp_path, warnings):
    data = result_to_dict(make_result())
    data["warnings"] = warnings
    with pytest.raises(ResultFormatError, match="key 'warnings' must be a list of strings"):
        read_result(written(tmp_path, data))


def test_inconsistent_D_inv(tmp_path):
    data = result_to_dict(make_result())
    data["D_inv"] = np.round(np.array(data["D_inv"]), 3).tolist()
    with pytest.raises(ResultFormatError, match="key 'D_inv' is not the inverse of 'D'"):
        read_result(written(tmp_path, data))


def test_singular_D(tmp_path):
    data = result_to_dict(make_result())
    data["D"] = [[1, 0, 0], [0, 1, 0], [0, 0, 0]]
    with pytest.raises(ResultFormatError, match="r.json: D is singular"):
        read_result(written(tmp_path, data))


def test_m_n_not_unit_names_file(tmp_path):
    data = result_to_dict(make_result())
    data["m_n"] = [2.0, 0.0, 0.0]
    with pytest.raises(ResultFormatError, match=r"r\.json: m_n must have unit norm"):
        read_result(written(tmp_path, data))


def test_non_finite_in_extra_names_path(tmp_path):
    data = result_to_dict(make_result())
    data["stats"] = {"history": [1.0, float("inf")]}
    with pytest.raises(ResultFormatError, match=r"key 'stats\.history\[1\]' holds inf"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize("key", ["D", "D_inv", "o", "m_n", "gyro_bias"])
def test_integer_too_large_for_float64_names_key(tmp_path, key):
    data = result_to_dict(make_result())
    value = data[key]
    if key in ("D", "D_inv"):
        value[1][2] = 10**400  # valid JSON; float() of it overflows
    else:
        value[1] = 10**400
    with pytest.raises(ResultFormatError, match=rf"r\.json: key '{key}' holds a number too large"):
        read_result(written(tmp_path, data))


def test_integer_dip_too_large_for_float64(tmp_path):
    data = result_to_dict(make_result())
    data["dip_deg"] = 10**400
    with pytest.raises(ResultFormatError, match="key 'dip_deg' .* too large for a float64"):
        read_result(written(tmp_path, data))
    with pytest.raises(ResultFormatError, match="dip_deg is too large for a float64"):
        make_result(dip_deg=10**400)


def test_float_beyond_float64_is_not_finite(tmp_path):
    text = json.dumps(result_to_dict(make_result())).replace('"dip_deg": 70.0', '"dip_deg": 1e400')
    with pytest.raises(ResultFormatError, match="key 'dip_deg' must be a finite number, got inf"):
        read_result(written(tmp_path, text))


def test_integer_with_too_many_digits(tmp_path):
    text = json.dumps(result_to_dict(make_result())).replace("70.0", "7" * 5000)
    with pytest.raises(ResultFormatError, match="not a usable JSON file"):
        read_result(written(tmp_path, text))


def test_absurdly_nested_json(tmp_path):
    with pytest.raises(ResultFormatError, match="not a usable JSON file"):
        read_result(written(tmp_path, "[" * 100_000))


def test_m_n_must_agree_with_dip(tmp_path):
    data = result_to_dict(make_result())
    data["m_n"] = field_direction(np.deg2rad(60.0)).tolist()  # unit norm, wrong dip
    pattern = r"r\.json: m_n = .* does not agree with dip_deg = 70\.0"
    with pytest.raises(ResultFormatError, match=pattern):
        read_result(written(tmp_path, data))
    data["m_n"] = (-field_direction(np.deg2rad(70.0))).tolist()  # field pointing south and up
    with pytest.raises(ResultFormatError, match="does not agree with dip_deg"):
        read_result(written(tmp_path, data))


def test_m_n_agrees_with_dip_to_1e_6(tmp_path):
    data = result_to_dict(make_result())
    m_n = field_direction(np.deg2rad(70.0))
    data["m_n"] = np.round(m_n, 7).tolist()  # hand-rounded to 7 decimals: within 1e-6
    assert read_result(written(tmp_path, data)).dip_deg == 70.0
    data["m_n"] = np.round(m_n, 4).tolist()  # 4 decimals: off by up to 5e-5
    with pytest.raises(ResultFormatError, match="does not agree with dip_deg"):
        read_result(written(tmp_path, data))


@pytest.mark.parametrize("dip", [-90.0, 0.0, 90.0])
def test_dip_limits_are_accepted(dip):
    assert make_result(m_n=field_direction(np.deg2rad(dip)), dip_deg=dip).dip_deg == dip


@pytest.mark.parametrize("dip", [-90.5, 90.001, 110.0, 270.0])
def test_dip_outside_plus_minus_90_is_rejected(tmp_path, dip):
    m_n = field_direction(np.deg2rad(dip))
    with pytest.raises(ResultFormatError, match=r"dip_deg = .* is outside \[-90, 90\] degrees"):
        make_result(m_n=m_n, dip_deg=dip)
    data = result_to_dict(make_result())
    data["m_n"], data["dip_deg"] = m_n.tolist(), dip
    with pytest.raises(ResultFormatError, match=r"r\.json: dip_deg = .* is outside"):
        read_result(written(tmp_path, data))


def test_missing_file(tmp_path):
    with pytest.raises(ResultFileError, match=r"reading result .*nope\.json: no such file"):
        read_result(tmp_path / "nope.json")


def test_directory_instead_of_file(tmp_path):
    with pytest.raises(ResultFileError, match="it is a directory: give a file name"):
        read_result(tmp_path)


def test_write_into_missing_directory(tmp_path):
    path = tmp_path / "no" / "r.json"
    with pytest.raises(ResultFileError, match=r"writing result .*: directory .*no does not exist"):
        write_result(path, make_result())


def test_check_result_writable(tmp_path):
    check_result_writable(tmp_path / "r.json")
    assert not (tmp_path / "r.json").exists()
    with pytest.raises(ResultFileError, match=r"writing result .*r\.json: directory .* does not"):
        check_result_writable(tmp_path / "no" / "r.json")
    assert issubclass(ResultFileError, ResultFormatError)


def test_result_from_dict_default_source():
    with pytest.raises(ResultFormatError, match="^result: missing required key"):
        result_from_dict({})


# ---------------------------------------------------------------------------------------------
# Building and writing: invalid results are refused early


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"method": ""}, "method must be a non-empty string"),
        ({"D": np.eye(2)}, r"D must have shape \(3, 3\)"),
        ({"D": np.zeros((3, 3))}, "D is singular"),
        ({"o": [0.0, np.nan, 0.0]}, "o has non-finite entries"),
        ({"m_n": [1.0, 1.0, 0.0]}, "m_n must have unit norm"),
        ({"m_n": [1.0, 0.0, 0.0]}, "m_n = .* does not agree with dip_deg = 70.0"),
        ({"dip_deg": 60.0}, "does not agree with dip_deg = 60.0"),
        ({"dip_deg": 91.0}, r"dip_deg = 91.0 is outside \[-90, 90\]"),
        ({"dip_deg": float("nan")}, "dip_deg is not finite"),
        ({"dip_deg": "70"}, "dip_deg must be a number"),
        ({"gyro_bias": np.zeros(2)}, r"gyro_bias must have shape \(3,\)"),
        ({"warnings": "one"}, "warnings must be a list of strings"),
        ({"extra": {"D": 1}}, "extra key 'D' must be a string other than the required keys"),
        ({"extra": {"cost": np.float64("nan")}}, "key 'cost' holds nan"),
        ({"extra": {"x": object()}}, "key 'x' holds a object, which JSON cannot store"),
        ({"extra": {"x": {1: 2}}}, "key 'x' has non-string key 1"),
    ],
)
def test_constructor_rejects(changes, pattern):
    with pytest.raises(ResultFormatError, match=pattern):
        make_result(**changes)


def test_write_leaves_no_file_on_failure(tmp_path):
    r = make_result()
    # Bypass the constructor's check to simulate a result that cannot be encoded.
    object.__setattr__(r, "extra", {"bad": float("nan")})
    path = tmp_path / "r.json"
    with pytest.raises(ResultFormatError, match=r"writing result .*r\.json: cannot encode it"):
        write_result(path, r)
    assert not path.exists()
