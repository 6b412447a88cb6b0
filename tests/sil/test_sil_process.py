# SPDX-License-Identifier: Apache-2.0
"""magcal_evaluation.sil's process wrapper against the SIL device: its stderr never blocks it.

The SIL writes one stderr line per refused feed line; a pipe nobody reads while it runs
would fill (64 KB) and block it in fprintf, so the wrapper sends stderr to a file, which
stderr_text reads while it runs.
"""

from __future__ import annotations

import shutil

import pytest

from magcal.device.client import DeviceClient, StreamKind
from magcal.link import LINK_OPEN_TIMEOUT_S, open_link
from magcal_evaluation.sil import REPO_ROOT, SIL_BINARY
from magcal_evaluation.world import FeedClient, physical_line

#: Refused feed lines to send: each makes a stderr line of about 150 bytes, so well past 64 KB.
N_BAD_LINES = 2000
#: How long the SIL may take to work through them and send the good line's sample, s.
FEED_DONE_TIMEOUT_S = 20.0

pytestmark = pytest.mark.skipif(
    not SIL_BINARY.exists()
    and not ((REPO_ROOT / "mk" / "sil.mk").exists() and shutil.which("make")),
    reason="the SIL executable build/sil/magcal-sil is missing and cannot be built",
)


def test_many_refused_feed_lines_do_not_block_the_device(start_sil, tmp_path):
    sil = start_sil(tmp_path / "flash.bin")
    bad = [f"P {1000 + k} nan 0 0 0 0 0 0 0 0\n" for k in range(N_BAD_LINES)]
    good = physical_line(1000 + N_BAD_LINES, (2e-5, 0, 4e-5), (0, 0, 9.8), (0, 0, 0))
    with (
        DeviceClient(open_link(sil.url, LINK_OPEN_TIMEOUT_S)) as client,
        FeedClient("127.0.0.1", sil.feed_port) as feed,
    ):
        client.hello()
        client.stream_start(StreamKind.RAW)
        feed.send_lines([*bad, good])
        # The feed is read in order: the good line's sample comes after every refusal was
        # written to stderr (a device blocked on a full stderr pipe never sends it).
        s = client.read_stream(FEED_DONE_TIMEOUT_S)
        assert s.t_us == 1000 + N_BAD_LINES
        client.stream_stop()
        assert client.hello().version >= 1  # it still answers
    err = sil.stderr_text()  # readable while it runs
    assert err.count("skipped: P ") == N_BAD_LINES and len(err.encode()) > 64 * 1024
    assert f"magcal-sil: feed line {N_BAD_LINES}: status -2" in err
    assert sil.stop() == 0
