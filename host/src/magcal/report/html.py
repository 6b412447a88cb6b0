# SPDX-License-Identifier: Apache-2.0
"""The calibration report as one self-contained HTML page (``magcal report``).

Self-contained means the page needs nothing but itself: the CSS is inline, every figure is
a PNG in a ``data:`` URI, and there is no JavaScript and no external link, so it can be
mailed, archived or opened offline years later and look the same. The numbers and figures
come from ``contents.build_report``; this module only formats them and writes the file.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os

import numpy as np

from magcal import __version__
from magcal.calib.diagnostics import uncertainty
from magcal.io.result import REQUIRED_KEYS, result_to_dict
from magcal.io.session import check_writable, os_error_advice
from magcal.report.contents import Figure, Report, ReportError, SessionEvaluation


def write_report(path: str | os.PathLike, text: str) -> None:
    """Write the page (the text is complete before the file is opened, as for results)."""
    try:
        with open(path, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
    except OSError as exc:
        raise ReportError(
            f"writing report {os.fspath(path)}: {os_error_advice(exc, path, writing=True)}"
        ) from exc


def check_report_writable(path: str | os.PathLike) -> None:
    """Raise :class:`ReportError` unless the report can be written (before the slow part)."""
    check_writable(path, "writing report", ReportError)


# --------------------------------------------------------------------------------------------
# Formatting numbers


def value_pm(value: float, sigma: float | None) -> str:
    """ "0.98765 ± 0.00014": σ to two significant digits, the value to the same decimals.
    σ = inf (not identifiable) reads "± ∞"; no σ (None or NaN) gives the value alone."""
    if not math.isfinite(value):
        return "—"
    if sigma is None or math.isnan(sigma):
        return f"{value:.6g}"
    if math.isinf(sigma):
        return f"{value:.6g} ± ∞"
    if sigma <= 0.0:
        return f"{value:.6g} ± 0"
    decimals = min(15, max(0, 1 - math.floor(math.log10(sigma))))
    return f"{value:.{decimals}f} ± {sigma:.{decimals}f}"


def _percent(x: float) -> str:
    return f"{100.0 * x:.3g} %"


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


# --------------------------------------------------------------------------------------------
# Rendering

CSS = """
* { box-sizing: border-box; }
body { margin: 0; background: #eef1f5; color: #1f2733;
  font: 15px/1.45 "DejaVu Sans", "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1160px; margin: 0 auto; padding: 28px 36px 48px; background: #fff;
  box-shadow: 0 0 12px rgba(0, 0, 0, 0.06); }
h1 { font-size: 26px; margin: 0 0 4px; }
h2 { font-size: 20px; margin: 36px 0 12px; padding-bottom: 6px; border-bottom: 2px solid #d6dde7; }
h3 { font-size: 16px; margin: 22px 0 8px; color: #2c3e57; }
.subtitle { color: #5b6675; margin: 0 0 20px; font-size: 14px; }
.summary { border: 1px solid #c7d4e4; background: #f4f8fc; border-radius: 8px;
  padding: 16px 20px; }
.kpis { display: grid; grid-template-columns: repeat(5, minmax(0, 1fr)); gap: 14px 18px; }
.kpi .label { font-size: 12px; color: #5b6675; text-transform: uppercase;
  letter-spacing: 0.03em; }
.kpi .value { font-size: 19px; font-weight: 600; }
.kpi .detail { font-size: 12px; color: #5b6675; }
.good { color: #1b7a3d; } .poor { color: #b3261e; }
.box { border-radius: 6px; padding: 10px 14px; margin: 12px 0 0; }
.box.warn { background: #fff6e0; border-left: 5px solid #e0a100; }
.box.bad { background: #fdecea; border-left: 5px solid #c62828; }
.box.info { background: #eef4fb; border-left: 5px solid #5b8fd1; }
.box ul { margin: 4px 0 0; padding-left: 20px; }
table { border-collapse: collapse; margin: 6px 0 10px; font-size: 14px; }
th, td { padding: 4px 9px; border-bottom: 1px solid #e3e8ef; vertical-align: top; }
th { text-align: left; background: #f2f5f9; font-weight: 600; }
td.num { text-align: right; font-family: "DejaVu Sans Mono", Menlo, Consolas, monospace;
  font-size: 12.5px; white-space: nowrap; }
th.num { text-align: right; }
td.key { color: #3c4858; white-space: nowrap; }
.grid2 { display: grid; grid-template-columns: 1fr 1fr; gap: 8px 32px; }
.grid2 > div { min-width: 0; overflow-x: auto; }
p.note { font-size: 13px; color: #5b6675; }
.figs { display: grid; grid-template-columns: 1fr 1fr; gap: 20px; }
figure { margin: 0; border: 1px solid #e1e6ee; border-radius: 6px; padding: 10px; }
figure.wide { grid-column: 1 / -1; }
figure img { display: block; width: 100%; height: auto; }
figcaption { font-size: 13px; color: #4a5565; margin-top: 6px; }
figcaption b { color: #1f2733; }
pre { background: #f6f8fa; border: 1px solid #e1e6ee; padding: 10px; font-size: 12px;
  overflow-x: auto; }
footer { margin-top: 36px; font-size: 12px; color: #7a8594; }
"""


def _kpi(label: str, value: str, detail: str = "", cls: str = "") -> str:
    klass = f' class="value {cls}"' if cls else ' class="value"'
    detail_html = f'<div class="detail">{_e(detail)}</div>' if detail else ""
    return (
        f'<div class="kpi"><div class="label">{_e(label)}</div>'
        f"<div{klass}>{_e(value)}</div>{detail_html}</div>"
    )


def _table(header: list[str] | None, rows: list[list[str]], numeric_from: int | None = 1) -> str:
    """Rows of already-formatted text; columns from ``numeric_from`` on are right-aligned
    (None: none are). No header row when ``header`` is None."""
    width = len(header) if header else max((len(r) for r in rows), default=0)
    first_numeric = width if numeric_from is None else numeric_from

    def cell(tag: str, i: int, text: str) -> str:
        klass = "num" if i >= first_numeric else ("key" if tag == "td" and i == 0 else "")
        attr = f' class="{klass}"' if klass else ""
        return f"<{tag}{attr}>{_e(text)}</{tag}>"

    head = (
        "<thead><tr>" + "".join(cell("th", i, h) for i, h in enumerate(header)) + "</tr></thead>"
        if header
        else ""
    )
    body = "".join(
        "<tr>" + "".join(cell("td", i, c) for i, c in enumerate(row)) + "</tr>" for row in rows
    )
    return f"<table>{head}<tbody>{body}</tbody></table>"


def _sigma(report: Report, name: str) -> np.ndarray | None:
    return None if report.uncertainty is None else report.uncertainty.sigma[name]


def _matrix(M: np.ndarray, S: np.ndarray | None) -> str:
    rows = [
        [a] + [value_pm(float(M[i, j]), None if S is None else float(S[i, j])) for j in range(3)]
        for i, a in enumerate("xyz")
    ]
    return _table(["", "x", "y", "z"], rows)


def _summary(report: Report) -> str:
    r, fit, val, unc = report.result, report.fit, report.validation, report.uncertainty
    improved = fit.spread_after < fit.spread_before
    kpis = [
        _kpi("Method", r.method, f"{fit.n_samples} samples, {fit.duration_s:.1f} s"),
        _kpi(
            "Norm spread (std/mean)",
            f"{_percent(fit.spread_before)} → {_percent(fit.spread_after)}",
            "fit session, before → after",
            "good" if improved else "poor",
        ),
    ]
    if val is not None:
        kpis.append(
            _kpi(
                "Validation norm spread",
                f"{_percent(val.spread_before)} → {_percent(val.spread_after)}",
                f"{val.n_samples} samples not in the fit",
                "good" if val.spread_after < val.spread_before else "poor",
            )
        )
    dip_sigma = None if unc is None else float(unc.sigma["dip_deg"])
    kpis.append(_kpi("Dip angle", value_pm(r.dip_deg, dip_sigma) + "°", "positive down"))
    mis = uncertainty.misalignment_deg(r.D)
    if np.isfinite(mis).all():
        kpis.append(
            _kpi(
                "Misalignment",
                _pm(report, "misalignment_angle_deg", float(np.linalg.norm(mis))) + "°",
                "magnetometer vs body axes",
            )
        )
    if fit.dip_calibrated is not None and fit.dip_raw is not None:
        kpis.append(
            _kpi(
                "Inclination spread",
                f"{fit.dip_calibrated['std']:.3g}°",
                f"dip std per sample (raw {fit.dip_raw['std']:.3g}°)",
            )
        )
    if fit.innovations is not None:
        s = fit.innovations.std
        kpis.append(
            _kpi(
                "Innovations std",
                f"{s:.3f}",
                "1 when the model fits",
                "good" if 0.8 < s < 1.25 else "poor",
            )
        )
    if unc is not None:
        kpis.append(
            _kpi(
                "Identifiability",
                "all parameters" if unc.identifiable else "NOT identifiable",
                f"Hessian of {unc.n_samples} samples",
                "good" if unc.identifiable else "poor",
            )
        )
    kpis.append(_kpi("Warnings", str(len(r.warnings)), "", "poor" if r.warnings else "good"))
    parts = [f'<section class="summary"><div class="kpis">{"".join(kpis)}</div>']
    if r.warnings:
        items = "".join(f"<li>{_e(w)}</li>" for w in r.warnings)
        parts.append(
            f'<div class="box warn"><b>Warnings of the calibration</b><ul>{items}</ul></div>'
        )
    if unc is not None and not unc.identifiable:
        items = "".join(f"<li>{_e(d)}</li>" for d in unc.null_directions)
        parts.append(
            '<div class="box bad"><b>Not identifiable:</b> the ML cost has no curvature along '
            "these directions of θ (scaled units), so the data do not determine them:"
            f"<ul>{items}</ul></div>"
        )
    if report.notes:
        items = "".join(f"<li>{_e(n)}</li>" for n in report.notes)
        parts.append(f'<div class="box info"><b>Notes</b><ul>{items}</ul></div>')
    parts.append("</section>")
    return "".join(parts)


def _pm(report: Report, name: str, value: float, index: tuple = (), scale: float = 1.0) -> str:
    """``value ± σ`` with the σ of quantity ``name`` at ``index``, both times ``scale``."""
    sigma = _sigma(report, name)
    return value_pm(scale * value, None if sigma is None else scale * float(sigma[index]))


def _calibration(report: Report) -> str:
    r, unc = report.result, report.uncertainty
    unit = r.extra.get("mag_unit") or "the session's magnetometer unit"
    axes = ("x", "y", "z")
    if unc is None:
        sigma_text = "Values are ± one standard deviation where available (see the notes)."
    elif unc.identifiable:
        sigma_text = "Values are ± one standard deviation."
    else:
        sigma_text = (
            "Values are ± one standard deviation; ± ∞ marks what the data do not determine "
            "(see the summary)."
        )
    out = [
        "<h2>Calibration</h2>",
        "<p>Model <code>y = D R<sub>bn</sub> m<sup>n</sup> + o</code>; correction "
        "<code>m<sup>b</sup> = D<sup>−1</sup>(y − o)</code>: a unit field in the body frame "
        f"(the accelerometer's axes). D and o are in <b>{_e(unit)}</b>. {sigma_text}</p>",
        '<div class="grid2"><div><h3>D (magnetometer units per unit field)</h3>',
        _matrix(r.D, _sigma(report, "D")),
        "</div><div><h3>D<sup>−1</sup>, the correction matrix</h3>",
        _matrix(r.D_inv, _sigma(report, "D_inv")),
        "</div></div>",
    ]
    field_rows = [
        [f"offset o {a}", _pm(report, "o", float(r.o[i]), (i,))] for i, a in enumerate(axes)
    ]
    field_rows.append(["dip angle δ (°, positive down)", _pm(report, "dip_deg", r.dip_deg)])
    # m_n's y component is 0 by definition: no σ.
    field_rows.append(["field direction m_n x", _pm(report, "m_n", float(r.m_n[0]), (0,))])
    field_rows.append(["field direction m_n y", "0"])
    field_rows.append(["field direction m_n z", _pm(report, "m_n", float(r.m_n[2]), (2,))])
    rot_rows = []
    mis = uncertainty.misalignment_deg(r.D)
    if np.isfinite(mis).all():
        for i, a in enumerate(axes):
            rot_rows.append(
                [
                    f"misalignment about body {a} (°)",
                    _pm(report, "misalignment_deg", float(mis[i]), (i,)),
                ]
            )
        angle = float(np.linalg.norm(mis))
        rot_rows.append(["misalignment angle (°)", _pm(report, "misalignment_angle_deg", angle)])
    if r.gyro_bias is not None:
        deg = float(np.rad2deg(1.0))
        for i, a in enumerate(axes):
            rot_rows.append(
                [
                    f"gyroscope bias {a} (°/s)",
                    _pm(report, "gyro_bias", float(r.gyro_bias[i]), (i,), deg),
                ]
            )
    out += [
        '<div class="grid2"><div><h3>Offset and field</h3>',
        _table(["quantity", "value"], field_rows),
        "</div><div><h3>Misalignment and gyroscope bias</h3>",
        _table(["quantity", "value"], rot_rows) if rot_rows else "<p>Not in the result.</p>",
        "</div></div>",
        '<p class="note">Misalignment: with the left polar decomposition D = P U (P symmetric '
        "positive definite: scale factors and soft iron; U a rotation), the rotation of the "
        "magnetometer's axes against the body axes is Uᵀ, shown as a rotation vector in "
        "degrees.</p>",
    ]
    if unc is not None:
        noise_rows = []
        for key, label, scale in (
            ("noise_std_gyr", "gyroscope (°/s)", float(np.rad2deg(1.0))),
            ("noise_std_acc", "accelerometer (m/s²)", 1.0),
            ("noise_std_mag", "magnetometer (its unit)", 1.0),
        ):
            values = unc.values[key]
            noise_rows.append(
                [label] + [_pm(report, key, float(values[i]), (i,), scale) for i in range(3)]
            )
        out += [
            "<h3>Noise standard deviations (ML estimates)</h3>",
            _table(["sensor", "x", "y", "z"], noise_rows),
        ]
    return "".join(out)


def _run_facts(report: Report) -> list[list[str]]:
    """Rows about the calibration run, from the result's optional keys."""
    x = report.result.extra
    rows = []
    opt = x.get("optimizer")
    if isinstance(opt, dict):
        rows.append(
            [
                "ML optimiser",
                f"{opt.get('iterations')} iterations, stopped on "
                f"'{opt.get('stopping_rule')}' ({opt.get('gradient')} gradient)",
            ]
        )
    if isinstance(x.get("negative_log_likelihood"), (int, float)):
        rows.append(["−log-likelihood V(θ̂)", f"{x['negative_log_likelihood']:.6f}"])
    obs = x.get("observability")
    if isinstance(obs, dict) and isinstance(obs.get("total_rotation_rad"), (int, float)):
        rows.append(["total rotation", f"{np.rad2deg(obs['total_rotation_rad']):.0f}°"])
    init = x.get("initial")
    if isinstance(init, dict) and init.get("noise_source"):
        rows.append(["noise initialised from", str(init["noise_source"])])
    secs = x.get("seconds")
    if isinstance(secs, dict):
        total = sum(v for v in secs.values() if isinstance(v, (int, float)))
        rows.append(["calibration time", f"{total:.2f} s"])
    return rows


def _uncertainty(report: Report) -> str:
    unc = report.uncertainty
    out = ["<h2>Uncertainty</h2>"]
    if unc is None:
        out.append(
            "<p>Not computed: the result lacks what the ML cost needs (see the notes above).</p>"
        )
        return "".join(out)
    out.append(
        "<p>Standard deviations are the square roots of the diagonal of the inverse Hessian of "
        "the ML cost (the negative log-likelihood of eq. 6 plus the gyroscope-noise prior, i.e. "
        "what the optimiser minimises) at the result's parameters on the fit session; derived "
        "quantities (D<sup>−1</sup>, the misalignment, m<sub>n</sub>, noise standard "
        "deviations) by linearisation. The Hessian is central differences of the exact "
        f"reverse-mode gradient ({unc.gradient_evaluations} gradient passes, "
        f"{unc.seconds:.2f} s for {unc.n_samples} samples). They describe the noise of the "
        "estimate, not model errors such as unmodelled accelerations.</p>"
    )
    rows = [
        ["Newton step to the cost's minimum", f"{unc.newton_step_sigma:.3g} σ"],
        ["smallest eigenvalue of the scaled Hessian", f"{unc.min_scaled_eigenvalue:.3g}"],
        ["identifiable", "yes" if unc.identifiable else "no: " + "; ".join(unc.null_directions)],
    ]
    out.append(_table(None, rows, numeric_from=None))
    if not unc.at_minimum:
        out.append(
            '<div class="box warn">The result is not at the minimum of the ML cost on this '
            f"session (a Newton step of {unc.newton_step_sigma:.3g} standard deviations "
            "would move it): it is not this session's ML estimate.</div>"
        )
    for note in unc.notes:
        out.append(f'<div class="box info">{_e(note)}</div>')
    return "".join(out)


def _session_table(ev: SessionEvaluation, extra_rows: list[list[str]] = ()) -> str:
    """The session's file, size and metadata lines, then ``extra_rows``."""
    rows = [
        ["file", ev.path],
        ["samples", f"{ev.n_samples}"],
        ["duration", f"{ev.duration_s:.2f} s"],
        ["sample rate", f"{ev.rate_hz:.1f} Hz"],
    ]
    rows += [[f"# {k}", v] for k, v in ev.meta.items()]
    return _table(None, rows + list(extra_rows), numeric_from=None)


def _evaluation_table(ev: SessionEvaluation) -> str:
    rows = [
        [
            "field norm mean (raw units → calibrated)",
            f"{ev.norm_before['mean']:.6g}",
            f"{ev.norm_after['mean']:.6g}",
        ],
        ["field norm spread (std/mean)", _percent(ev.spread_before), _percent(ev.spread_after)],
    ]
    if ev.dip_raw is not None and ev.dip_calibrated is not None:
        rows.append(
            ["dip angle mean (°)", f"{ev.dip_raw['mean']:.4g}", f"{ev.dip_calibrated['mean']:.4f}"]
        )
        rows.append(
            ["dip angle std (°)", f"{ev.dip_raw['std']:.3g}", f"{ev.dip_calibrated['std']:.3g}"]
        )
        rows.append(
            ["samples for the dip", f"{ev.dip_raw['count']}", f"{ev.dip_calibrated['count']}"]
        )
    out = _table(["", "before (raw)", "after"], rows)
    if ev.innovations is not None:
        s = ev.innovations
        out += _table(
            ["normalised innovations", "mean", "std", "|x| > 3"],
            [
                [
                    "ML filter with the result",
                    f"{s.mean:.3f}",
                    f"{s.std:.3f}",
                    _percent(s.fraction_outside_3),
                ]
            ],
        )
    return out


def png_size(png: bytes) -> tuple[int, int]:
    """(width, height) in pixels from a PNG's IHDR chunk."""
    if png[:8] != b"\x89PNG\r\n\x1a\n" or png[12:16] != b"IHDR":
        raise ValueError("not a PNG file")
    return int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")


def _figures(figs: list[Figure]) -> str:
    out = ['<div class="figs">']
    for f in figs:
        wide = ' class="wide"' if f.wide else ""
        data = base64.b64encode(f.png).decode("ascii")
        # width/height give the browser the aspect ratio before (or without) decoding: the
        # layout does not jump, and a broken image keeps its place.
        w, h = png_size(f.png)
        out.append(
            f'<figure{wide}><img alt="{_e(f.title)}" width="{w}" height="{h}" '
            f'src="data:image/png;base64,{data}"><figcaption><b>{_e(f.title)}.</b> '
            f"{_e(f.caption)}</figcaption></figure>"
        )
    out.append("</div>")
    return "".join(out)


def _result_json(report: Report) -> str:
    data = result_to_dict(report.result)
    lines = []
    for key in REQUIRED_KEYS:
        value = data[key]
        if isinstance(value, list) and value and isinstance(value[0], list):
            rows = ",\n    ".join(json.dumps(row) for row in value)
            text = f"[\n    {rows}\n  ]"
        else:
            text = json.dumps(value, ensure_ascii=False)
        lines.append(f"  {json.dumps(key)}: {text}")
    body = "{\n" + ",\n".join(lines) + "\n}"
    return (
        "<h2>Result file</h2>"
        f"<p>The required keys of <code>{_e(report.result_path)}</code>, with every digit "
        "stored:</p>"
        f"<pre>{_e(body)}</pre>"
    )


def render_html(report: Report) -> str:
    """The page (UTF-8 text)."""
    fit, val = report.fit, report.validation
    body = [
        "<h1>Magnetometer calibration report</h1>",
        f'<p class="subtitle">Result <b>{_e(report.result_path)}</b> · fit session '
        f"<b>{_e(fit.path)}</b>"
        + (f" · validation session <b>{_e(val.path)}</b>" if val else "")
        + f" · made {_e(report.created)} by magcal {_e(__version__)}</p>",
        _summary(report),
        _calibration(report),
        _uncertainty(report),
        "<h2>Fit session</h2>",
        '<div class="grid2"><div>',
        _session_table(fit, _run_facts(report)),
        "</div><div>",
        _evaluation_table(fit),
        "</div></div>",
        _figures(fit.figures),
    ]
    if val is not None:
        body += [
            "<h2>Validation session</h2>",
            "<p>The calibration applied to data not used for the fit: the field norm, the ML "
            "filter's residuals and the inclination should look as good as on the fit "
            "session. The filter uses the result's gyroscope bias, which may have drifted "
            "since the fit session.</p>",
            '<div class="grid2"><div>',
            _session_table(val),
            "</div><div>",
            _evaluation_table(val),
            "</div></div>",
            _figures(val.figures),
        ]
    body.append(_result_json(report))
    body.append(
        "<footer>Made by <code>magcal report</code>. Method: Kok &amp; Schön (2016), "
        "<i>Magnetometer calibration using inertial sensors</i>, IEEE Sensors Journal 16(14). "
        "This page is self-contained: no scripts, no external resources.</footer>"
    )
    title = f"magcal report: {report.result_path}"
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_e(title)}</title><style>{CSS}</style></head>"
        f"<body><main>{''.join(body)}</main></body></html>\n"
    )
