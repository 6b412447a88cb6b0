# SPDX-License-Identifier: Apache-2.0
"""``magcal report``: a self-contained page with the result's numbers, their σ, the figures, the
validation on a held-out session, and clear refusals for inputs that do not belong together."""

from __future__ import annotations

import base64
import dataclasses
import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from magcal.calib.calibrate import calibrate
from magcal.calib.diagnostics import uncertainty
from magcal.cli import EXIT_ERROR, main
from magcal.io.result import read_result, write_result
from magcal.io.session import read_session, session_from_arrays, write_session
from magcal.report import contents, html, plots
from magcal.sim.scenarios import preset, simulate

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: The fit session is the first FIT_S seconds of a simulated recording, the validation
#: session the rest: the same sensor, other motion and noise, not used for the fit.
FIT_S = 32.0


def split_session(session, t_split):
    k = int(np.searchsorted(session.t, t_split))
    part = lambda sl: session_from_arrays(  # noqa: E731
        session.t[sl], session.gyr[sl], session.acc[sl], session.mag[sl], session.meta
    )
    return part(slice(0, k)), part(slice(k, None))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    recording, _ = simulate(preset("mems", duration_s=45), seed=5)
    fit, held_out = split_session(recording, FIT_S)
    write_session(d / "fit.csv", fit)
    write_session(d / "val.csv", held_out)
    cal = calibrate(read_session(d / "fit.csv"), "ml")
    write_result(d / "result.json", cal.result)
    return d


def run(capsys, *args):
    code = main(["report", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def page(files):
    code = main(
        [
            "report",
            str(files / "result.json"),
            str(files / "fit.csv"),
            "-o",
            str(files / "report.html"),
            "--validate",
            str(files / "val.csv"),
        ]
    )
    assert code == 0
    return (files / "report.html").read_text(encoding="utf-8")


class Resources(HTMLParser):
    """Every URL-bearing attribute and every tag name of a page."""

    def __init__(self):
        super().__init__()
        self.urls: list[tuple[str, str, str]] = []
        self.tags: set[str] = set()
        self.images: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        for name, value in attrs:
            if name in ("src", "href", "srcset", "poster", "data", "action", "background"):
                self.urls.append((tag, name, value or ""))
            if tag == "img" and name == "src":
                self.images.append(value or "")


def parse(text):
    p = Resources()
    p.feed(text)
    return p


def test_the_page_is_self_contained(page):
    res = parse(page)
    assert "script" not in res.tags and "link" not in res.tags and "iframe" not in res.tags
    assert not re.search(r"https?://|@import|url\(", page, re.IGNORECASE)
    assert res.urls and all(tag == "img" and name == "src" for tag, name, _ in res.urls)
    for src in res.images:
        assert src.startswith("data:image/png;base64,")
        png = base64.b64decode(src.removeprefix("data:image/png;base64,"), validate=True)
        assert png[:8] == PNG_MAGIC
        width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
        assert width > 300 and height > 200  # the IHDR of a real figure


def test_the_page_holds_the_result_with_every_digit_and_its_sigma(files, page, capsys):
    result = read_result(files / "result.json")
    stored = json.loads((files / "result.json").read_text())
    for key in ("D", "D_inv", "o", "m_n", "gyro_bias"):
        for number in np.ravel(stored[key]):
            assert json.dumps(number) in page, (key, number)
    assert json.dumps(stored["dip_deg"]) in page
    u = uncertainty.calibration_uncertainty(result, read_session(files / "fit.csv"))
    for i in range(3):
        assert html.value_pm(result.o[i], u.sigma["o"][i]) in page
        for j in range(3):
            assert html.value_pm(result.D[i, j], u.sigma["D"][i, j]) in page
            assert html.value_pm(result.D_inv[i, j], u.sigma["D_inv"][i, j]) in page
    assert html.value_pm(result.dip_deg, float(u.sigma["dip_deg"])) in page
    sigmas = [float(s) for s in re.findall(r"± ([0-9.]+)", page)]
    assert len(sigmas) > 40 and all(np.isfinite(s) and s > 0 for s in sigmas)
    assert "not identifiable" not in page.lower()


def test_validation_section_shows_the_held_out_session(files, page):
    assert "<h2>Validation session</h2>" in page
    assert str(files / "val.csv") in page
    assert len(parse(page).images) == 8  # four figures per session
    assert page.count("<b>Normalised innovations.</b>") == 2  # one per session
    # Held-out data of the same sensor: the calibration holds there too.
    held_out = read_session(files / "val.csv")
    result = read_result(files / "result.json")
    after = np.linalg.norm((held_out.mag - result.o) @ result.D_inv.T, axis=1)
    assert after.std() / after.mean() < 0.02
    assert html._percent(after.std() / after.mean()) in page


def test_without_validate_there_is_no_validation_section(files, capsys):
    out = files / "fit-only.html"
    code, stdout, stderr = run(capsys, files / "result.json", files / "fit.csv", "-o", out)
    assert code == 0 and f"wrote {out}" in stdout
    text = out.read_text(encoding="utf-8")
    assert "Validation session" not in text
    assert len(parse(text).images) == 4
    assert "Hessian of the ML cost, gradient pass 1/68" in stderr  # progress of the slow part


# --------------------------------------------------------------------------------------------
# Refusals: each names the problem and writes nothing


def refused(capsys, tmp_path, *args, match):
    out = tmp_path / "refused.html"
    code, _, err = run(capsys, *args, "-o", out)
    assert code == EXIT_ERROR
    assert err.startswith("magcal report: ")
    assert re.search(match, err), err
    assert not out.exists()


def test_a_result_from_another_session_is_refused(files, capsys, tmp_path):
    refused(
        capsys,
        tmp_path,
        files / "result.json",
        files / "val.csv",
        match=r"was not calibrated from the session .*val\.csv.*--validate",
    )


def test_a_session_in_another_magnetometer_unit_is_refused(files, capsys, tmp_path):
    s = read_session(files / "val.csv")
    other = dataclasses.replace(s, meta={**s.meta, "mag_unit": "gauss"})
    write_session(tmp_path / "gauss.csv", other)
    for args in (
        (files / "result.json", tmp_path / "gauss.csv"),
        (files / "result.json", files / "fit.csv", "--validate", tmp_path / "gauss.csv"),
    ):
        refused(capsys, tmp_path, *args, match=r"unit is '.*' but the session .*'gauss'")


def test_swapped_or_wrong_file_types_are_named(files, capsys, tmp_path):
    refused(
        capsys,
        tmp_path,
        files / "fit.csv",
        files / "result.json",
        match=r"fit\.csv is a session CSV, not a result JSON: the order is",
    )
    refused(
        capsys,
        tmp_path,
        files / "result.json",
        files / "fit.csv",
        "--validate",
        files / "result.json",
        match=r"validation session .*result\.json is a result JSON",
    )
    (tmp_path / "notes.txt").write_text("hello\n")
    refused(capsys, tmp_path, tmp_path / "notes.txt", files / "fit.csv", match=r"not valid JSON")


def test_unreadable_inputs_and_unwritable_outputs_are_refused(files, capsys, tmp_path):
    refused(capsys, tmp_path, tmp_path / "missing.json", files / "fit.csv", match="no such file")
    refused(capsys, tmp_path, files / "result.json", tmp_path / "no.csv", match="no such file")
    code, _, err = run(
        capsys, files / "result.json", files / "fit.csv", "-o", tmp_path / "nodir" / "r.html"
    )
    assert code == EXIT_ERROR and "does not exist" in err
    before = (files / "fit.csv").read_bytes()
    code, _, err = run(capsys, files / "result.json", files / "fit.csv", "-o", files / "fit.csv")
    assert code == EXIT_ERROR and "one of the inputs" in err
    assert (files / "fit.csv").read_bytes() == before  # the session is never overwritten


# --------------------------------------------------------------------------------------------
# Results that are not ML estimates, and what the page says about them


def test_a_result_without_noise_covariances_gets_a_page_without_sigma(files, capsys, tmp_path):
    r = read_result(files / "result.json")
    extra = {k: v for k, v in r.extra.items() if not k.startswith("Sigma_")}
    write_result(tmp_path / "ckf.json", dataclasses.replace(r, method="ckf", extra=extra))
    code, _, _ = run(capsys, tmp_path / "ckf.json", files / "fit.csv", "-o", tmp_path / "c.html")
    text = (tmp_path / "c.html").read_text(encoding="utf-8")
    assert code == 0
    assert "no uncertainty and no innovations" in text and "Sigma_gyr" in text
    assert not re.search(r"\d ± \d", text) and "not identifiable" not in text.lower()
    assert len(parse(text).images) == 3  # no innovation histogram


def test_an_init_result_far_from_the_ml_minimum_gets_no_sigma(files, capsys, tmp_path):
    """The initial estimate is many standard deviations from the ML minimum: the page shows
    no σ for it, and says why."""
    init = calibrate(read_session(files / "fit.csv"), "init")
    write_result(tmp_path / "init.json", init.result)
    code, _, _ = run(capsys, tmp_path / "init.json", files / "fit.csv", "-o", tmp_path / "i.html")
    text = (tmp_path / "i.html").read_text(encoding="utf-8")
    assert code == 0
    assert "no uncertainty: the result (method &#x27;init&#x27;) is not a minimum" in text
    assert "calibrate with --method ml for standard deviations" in text
    assert not re.search(r"\d ± \d", text)


def test_a_result_far_from_the_ml_minimum_with_negative_curvature_gets_no_sigma(
    files, capsys, tmp_path
):
    r = read_result(files / "result.json")
    off = dataclasses.replace(r, method="two-step", gyro_bias=r.gyro_bias + [0.0, 0.01, 0.0])
    write_result(tmp_path / "off.json", off)
    code, _, _ = run(capsys, tmp_path / "off.json", files / "fit.csv", "-o", tmp_path / "o.html")
    text = (tmp_path / "o.html").read_text(encoding="utf-8")
    assert code == 0
    assert "no uncertainty: the result (method &#x27;two-step&#x27;) is not a minimum" in text
    assert "negative curvature along" in text and "bias_y" in text
    assert not re.search(r"\d ± \d", text) and "NOT identifiable" not in text


def test_another_methods_result_at_the_ml_minimum_keeps_its_sigma(files, capsys, tmp_path):
    r = read_result(files / "result.json")
    write_result(tmp_path / "same.json", dataclasses.replace(r, method="two-step"))
    code, _, _ = run(capsys, tmp_path / "same.json", files / "fit.csv", "-o", tmp_path / "s.html")
    text = (tmp_path / "s.html").read_text(encoding="utf-8")
    assert code == 0
    assert "is not a minimum" not in text and re.search(r"\d ± \d", text)


def test_a_non_identifiable_direction_is_flagged_on_the_page(files):
    report = contents.build_report(
        read_result(files / "result.json"),
        read_session(files / "fit.csv"),
        result_path="result.json",
        session_path="fit.csv",
    )
    u = report.uncertainty
    sigma = {**u.sigma, "o": np.array([u.sigma["o"][0], np.inf, u.sigma["o"][2]])}
    flagged = dataclasses.replace(
        report,
        uncertainty=dataclasses.replace(
            u,
            sigma=sigma,
            null_directions=["0.71·o1 − 0.70·D11"],
            notes=["the result comes from method 'x', not ml"],
        ),
    )
    text = html.render_html(flagged)
    assert "NOT identifiable" in text and "0.71·o1 − 0.70·D11" in text
    assert "the result comes from method &#x27;x&#x27;, not ml" in text
    assert f"{report.result.o[1]:.6g} ± ∞" in text and "± ∞ marks what the data" in text
    assert "NOT identifiable" not in html.render_html(report)


def test_value_pm_rounds_to_two_significant_digits_of_sigma():
    assert html.value_pm(1.0118852, 0.000123) == "1.01189 ± 0.00012"
    assert html.value_pm(-48.123456, 0.0567) == "-48.123 ± 0.057"
    assert html.value_pm(1234.5, 12.3) == "1234 ± 12"
    assert html.value_pm(0.5, None) == "0.5"
    assert html.value_pm(0.5, float("inf")) == "0.5 ± ∞"
    assert html.value_pm(float("nan"), 0.1) == "—"


def test_plot_dip_angles_writes_a_png_and_refuses_a_non_finite_estimate(tmp_path):
    rng = np.random.default_rng(0)
    raw, cal = rng.uniform(-60, 80, 500), 71.6 + 0.3 * rng.normal(size=500)
    out = plots.plot_dip_angles(raw, cal, 71.6, tmp_path / "dip.png")
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert html.png_size(out.read_bytes()) == (1080, 432)  # 9 × 3.6 in at plots.DPI
    with pytest.raises(ValueError, match="dip_estimate_deg must be finite"):
        plots.plot_dip_angles(raw, cal, float("nan"), tmp_path / "bad.png")
    with pytest.raises(ValueError, match="non-finite"):
        plots.plot_dip_angles(np.array([np.nan]), cal, 71.6, tmp_path / "bad.png")
