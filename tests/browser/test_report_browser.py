# SPDX-License-Identifier: Apache-2.0
"""``magcal report``'s page in a real browser: Debian's Chromium, headless.

Two renderings of the same page are compared: as written, and a copy whose images are
broken (their PNG data replaced). Where the page places its figures, the first must show the
figures' colours and many distinct colours, the second none of that, so a page whose images
are missing, undecodable or laid out off-screen fails. A third copy, with a small probe script
added (the page itself has none), reports through ``--dump-dom`` that every image decoded
(naturalWidth > 0) and where it lies on the page.

Chromium comes from ``make deps-browser`` (Debian's ``chromium``). Without it, plain
``pytest`` skips, naming that target; under ``make test`` (MAGCAL_REQUIRE_BROWSER=1) or in CI
(CI=true) a missing Chromium fails the test.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg
from matplotlib.colors import to_rgb

from magcal.calib.calibrate import calibrate
from magcal.cli import main
from magcal.io.result import write_result
from magcal.io.session import read_session, session_from_arrays, write_session
from magcal.report import plots
from magcal.sim.scenarios import preset, simulate

REQUIRE_ENV = "MAGCAL_REQUIRE_BROWSER"
CHROMIUM_ENV = "MAGCAL_CHROMIUM"
CHROMIUM_TIMEOUT_S = 120.0
WINDOW_WIDTH_PX = 1280
#: Window height of the probe run; the screenshots use the page's own height.
PROBE_HEIGHT_PX = 4000
#: Flags for a hermetic headless run: no network, no first-run or sync machinery, and a
#: private profile directory per run.
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",  # CI runs as root, where Chromium's sandbox refuses to start
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
)
#: The figures' line and marker colours (matplotlib's tab:red and tab:blue), and how far
#: (RGB distance) a resampled or alpha-blended pixel may be from them.
PLOT_COLOURS_RGB = 255.0 * np.array([to_rgb(plots.RAW_COLOR), to_rgb(plots.CALIBRATED_COLOR)])
PLOT_COLOUR_TOLERANCE = 90.0  # the histograms' bars are drawn with alpha 0.7 (distance 82)

PROBE_SCRIPT = """<script>
window.addEventListener("load", function () {
  var images = document.images;
  for (var i = 0; i < images.length; i++) {
    var img = images[i], r = img.getBoundingClientRect();
    img.setAttribute("data-probe", [img.complete ? 1 : 0, img.naturalWidth, img.naturalHeight,
      Math.round(r.left + window.scrollX), Math.round(r.top + window.scrollY),
      Math.round(r.width), Math.round(r.height)].join(","));
  }
  document.body.setAttribute("data-probe-height", document.documentElement.scrollHeight);
});
</script>"""


def chromium() -> str:
    """The Chromium binary; skips (or fails, when required) if there is none."""
    path = os.environ.get(CHROMIUM_ENV) or shutil.which("chromium")
    if path and Path(path).is_file():
        return path
    missing = "Chromium not found (Debian's chromium): run `make deps-browser`"
    if os.environ.get(REQUIRE_ENV) == "1" or os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{missing}; it is required here ({REQUIRE_ENV}=1 or CI=true)")
    pytest.skip(missing)


def run_chromium(binary: str, work: Path, page: Path, *args: str) -> str:
    profile = work / f"profile-{len(list(work.glob('profile-*')))}"
    cmd = [binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args, page.as_uri()]
    done = subprocess.run(
        cmd, capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S, check=False
    )
    if done.returncode != 0:
        pytest.fail(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return done.stdout


@pytest.fixture(scope="module")
def browser():
    return chromium()


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("browser")


@pytest.fixture(scope="module")
def page(browser, work) -> Path:
    """A report with a validation session: the first 25 s of a recording for the fit, the
    rest held out."""
    recording, _ = simulate(preset("mems", duration_s=35), seed=8)
    k = int(np.searchsorted(recording.t, 25.0))
    for name, sl in (("fit.csv", slice(0, k)), ("val.csv", slice(k, None))):
        part = session_from_arrays(
            recording.t[sl], recording.gyr[sl], recording.acc[sl], recording.mag[sl], recording.meta
        )
        write_session(work / name, part)
    write_result(work / "result.json", calibrate(read_session(work / "fit.csv"), "ml").result)
    out = work / "report.html"
    args = ["report", str(work / "result.json"), str(work / "fit.csv"), "-o", str(out)]
    assert main([*args, "--validate", str(work / "val.csv")]) == 0
    return out


@pytest.fixture(scope="module")
def probe(browser, work, page):
    """(page height in px, [(complete, naturalWidth, naturalHeight, x, y, w, h)] per image)."""
    text = page.read_text(encoding="utf-8")
    assert "<script" not in text  # the probe goes into a copy only
    probed = work / "probe.html"
    probed.write_text(text.replace("</body>", PROBE_SCRIPT + "</body>"), encoding="utf-8")
    dom = run_chromium(
        browser,
        work,
        probed,
        f"--window-size={WINDOW_WIDTH_PX},{PROBE_HEIGHT_PX}",
        "--virtual-time-budget=10000",
        "--dump-dom",
    )
    height = re.search(r'data-probe-height="(\d+)"', dom)
    assert height, "the probe script did not run: no data-probe-height in the DOM"
    images = [tuple(map(int, m.split(","))) for m in re.findall(r'data-probe="([\d,]+)"', dom)]
    return int(height.group(1)), images


def screenshot(browser, work, page: Path, height: int) -> np.ndarray:
    png = work / f"{page.stem}.png"
    run_chromium(
        browser,
        work,
        page,
        f"--window-size={WINDOW_WIDTH_PX},{height}",
        f"--screenshot={png}",
    )
    rgb = mpimg.imread(png)[..., :3]
    return np.round(rgb * 255.0).astype(np.int16)


def plot_colour_mask(shot: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels within PLOT_COLOUR_TOLERANCE of a figure colour."""
    mask = np.zeros(shot.shape[:2], bool)
    for colour in PLOT_COLOURS_RGB:
        d2 = np.sum((shot.astype(np.float32) - colour.astype(np.float32)) ** 2, axis=-1)
        mask |= d2 < PLOT_COLOUR_TOLERANCE**2
    return mask


def distinct_colours(region: np.ndarray) -> int:
    flat = region.reshape(-1, 3).astype(np.int64)
    return int(np.unique(flat[:, 0] << 16 | flat[:, 1] << 8 | flat[:, 2]).size)


def test_every_figure_decodes_in_chromium(probe, page):
    _, images = probe
    n_img = page.read_text(encoding="utf-8").count("<img ")
    assert n_img == 8 and len(images) == n_img
    for complete, natural_w, natural_h, _, _, w, h in images:
        assert complete == 1 and natural_w > 300 and natural_h > 200
        assert w > 400 and h > 200  # laid out at a readable size


def test_screenshot_shows_the_figures_where_the_page_places_them(browser, work, page, probe):
    height, images = probe
    shot = screenshot(browser, work, page, height)
    assert shot.shape[:2] == (height, WINDOW_WIDTH_PX)
    broken = work / "broken.html"
    text = re.sub(
        r"data:image/png;base64,[A-Za-z0-9+/=]+",
        "data:image/png;base64,AAAA",
        page.read_text(encoding="utf-8"),
    )
    broken.write_text(text, encoding="utf-8")
    shot_broken = screenshot(browser, work, broken, height)

    assert distinct_colours(shot) > 2000  # not a blank page
    coloured, coloured_broken = plot_colour_mask(shot), plot_colour_mask(shot_broken)
    for _, _, _, x, y, w, h in images:
        assert y + h <= height and x + w <= WINDOW_WIDTH_PX, "a figure lies off the page"
        n = int(coloured[y : y + h, x : x + w].sum())
        n_broken = int(coloured_broken[y : y + h, x : x + w].sum())
        # Measured: 1,900 to 34,000 with the figures; 0 with them broken.
        assert n > 500, f"figure at y={y}: only {n} pixels in the plot colours"
        assert n_broken * 20 < n, f"figure at y={y}: {n_broken} plot-coloured pixels when broken"
    # Outside the figures the two renderings are the same page.
    mask = np.ones(shot.shape[:2], bool)
    for *_, y, _, h in images:
        mask[max(0, y - 12) : y + h + 120, :] = False  # the figure, its caption and frame
    assert np.mean(np.any(shot != shot_broken, axis=-1)[mask]) < 0.01
