# SPDX-License-Identifier: Apache-2.0
"""magcal.device.flash's outcomes against the fake device (tests/fake_device.py): the backup
file is never overwritten and leaves nothing behind on failure; clients made by reconnect are
closed when recovery fails; a recovery before the backup step reports no backup; a commit
answered E_OUTCOME_UNKNOWN is settled by a reset and a read-back (SPEC §5)."""

from __future__ import annotations

import errno
import os
import re

import numpy as np
import pytest

from magcal import cli
from magcal.calib.frames import field_direction
from magcal.commands.flash import device as flash_command
from magcal.device import fixed_point
from magcal.device.client import ClientConfig, DeviceClient, Scale
from magcal.device.flash import FlashError, FlashInterruptedError, flash_parameters, read_backup
from magcal.device.generated import Status, Unit
from magcal.io.result import CalibrationResult, write_result
from magcal.link import LinkClosedError, LinkTimeoutError
from tests.fake_device import FakeDevice, LossyLink, MemoryLink, serve_tcp

FAST = ClientConfig(request_timeout_s=0.02, request_retries=3, reset_recovery_timeout_s=0.5)


def blob_for(gain: float, offset=(10.0, -20.0, 5.0)) -> bytes:
    return fixed_point.encode(fixed_point.from_calibration(np.eye(3) * gain, np.array(offset)))


OLD = blob_for(1.0 / 500)
NEW = blob_for(1.0 / 450, (3.0, 4.0, -7.5))


def client_for(dev: FakeDevice) -> DeviceClient:
    return DeviceClient(MemoryLink(dev), FAST, first_seq=100)


class DeadLink:
    """A link that opens but never answers; ``opened`` lists every one made."""

    url = "dead://"

    def __init__(self, opened: list[DeadLink]) -> None:
        self.closed = False
        opened.append(self)

    def write(self, data, timeout_s=None):
        if self.closed:
            raise LinkClosedError(f"write {self.url}: closed", self.url)

    def read(self, timeout_s, max_bytes=4096):
        if self.closed:
            raise LinkClosedError(f"read {self.url}: closed", self.url)
        raise LinkTimeoutError(f"read {self.url}: nothing", self.url)

    def close(self):
        self.closed = True


class CutLink(MemoryLink):
    """A MemoryLink that is gone (closed) as soon as ``when(device)`` holds after a write (with
    ``before``: at the first write after it holds; the response to the write before comes)."""

    def __init__(self, device: FakeDevice, when, before: bool = False) -> None:
        super().__init__(device)
        self.when, self.before = when, before

    def write(self, data, timeout_s=None):
        if self.before and self.when(self.device):
            self.closed = True
        super().write(data, timeout_s)
        if not self.before and self.when(self.device):
            self.closed = True


# ----------------------------------------------------------------------------- backup file
def test_backup_never_overwrites_a_file_created_while_it_is_written(tmp_path, monkeypatch):
    path = tmp_path / "b.json"
    real_fsync = os.fsync

    def fsync_then_someone_creates_path(fd):
        real_fsync(fd)
        if not path.exists():
            path.write_text("theirs")

    monkeypatch.setattr(os, "fsync", fsync_then_someone_creates_path)
    dev = FakeDevice(active_blob=OLD)
    with pytest.raises(FlashError, match="b.json exists; nothing was written to the device"):
        flash_parameters(client_for(dev), NEW, 1, path)
    assert path.read_text() == "theirs"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.json"]  # no temporary file left
    assert dev.acted["param_set"] == 0 and dev.flash == OLD


def test_backup_failure_leaves_no_temporary_file(tmp_path, monkeypatch):
    def fsync_fails(fd):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(os, "fsync", fsync_fails)
    dev = FakeDevice(active_blob=OLD)
    with pytest.raises(FlashError, match="cannot save the backup to .*b.json .*Input/output"):
        flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    assert list(tmp_path.iterdir()) == []
    assert dev.acted["param_set"] == 0


def test_backup_without_hard_links_copies_and_never_overwrites(tmp_path, monkeypatch):
    def no_hard_links(src, dst):
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_hard_links)  # as on a FAT file system
    dev = FakeDevice(active_blob=OLD)
    r = flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    assert r.active == "new" and read_backup(tmp_path / "b.json")["blob"] == OLD
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.json"]
    with pytest.raises(FlashError, match="b.json exists; nothing was written to the device"):
        flash_parameters(client_for(dev), OLD, 1, tmp_path / "b.json")
    assert read_backup(tmp_path / "b.json")["blob"] == OLD and dev.flash == NEW


# ----------------------------------------------------------------------------- open links
@pytest.mark.parametrize(
    ("cut_when", "before"),
    [
        pytest.param(lambda dev: dev.acted["param_commit"] > 0, False, id="at-commit"),
        pytest.param(lambda dev: dev.resets > 0, True, id="hello-after-reset"),
        pytest.param(lambda dev: dev.acted["param_set"] > 0, False, id="before-commit"),
    ],
)
def test_failed_recovery_closes_every_reconnected_client(tmp_path, cut_when, before):
    """The link goes after a step; every reconnection opens a link that never answers (the
    recovery's hello, or the hello after the reset, times out): all of them are closed, so
    the next connection to a one-client device (the SIL) is not blocked."""
    dev = FakeDevice(active_blob=OLD)
    opened: list[DeadLink] = []
    fast = ClientConfig(request_timeout_s=0.02, request_retries=1, reset_recovery_timeout_s=0.3)
    first = DeviceClient(CutLink(dev, cut_when, before), fast, first_seq=1)
    with pytest.raises(FlashInterruptedError, match="link failure at") as info:
        flash_parameters(
            first,
            NEW,
            1,
            tmp_path / "b.json",
            reconnect=lambda: DeviceClient(DeadLink(opened), fast),
        )
    assert info.value.active in ("old", "unknown")
    if before:
        assert info.value.step == "hello after reset"
    assert opened and [link.closed for link in opened] == [True] * len(opened)
    assert first.link.closed


def test_client_reconnected_after_reset_is_closed_when_the_commit_did_not_take(tmp_path):
    class Forgetful(FakeDevice):
        def _on_param_commit(self, f):
            return {"status": Status.OK}  # says stored, stores nothing

    dev = Forgetful(active_blob=OLD)
    links: list[MemoryLink] = []

    def reconnect() -> DeviceClient:
        links.append(MemoryLink(dev))
        return DeviceClient(links[-1], FAST, first_seq=900)

    # The device restarts and the link goes with it (a USB device re-enumerating).
    first = DeviceClient(CutLink(dev, lambda d: d.resets > 0, before=True), FAST, first_seq=1)
    with pytest.raises(FlashError, match="uses its old set, not the new one"):
        flash_parameters(first, NEW, 1, tmp_path / "b.json", reconnect=reconnect)
    assert len(links) == 1 and links[0].closed


# ----------------------------------------------------------------------------- no backup
def test_recovery_before_the_backup_step_reports_no_backup(tmp_path, capsys):
    """The link goes during info (before the backup) on a device that already holds the new
    set: the recovery finds the new set active, and the result names no backup file."""
    dev = FakeDevice(active_blob=NEW)
    link = LossyLink(MemoryLink(dev), disconnect_after=40)
    r = flash_parameters(
        DeviceClient(link, FAST, first_seq=5),
        NEW,
        1,
        tmp_path / "b.json",
        reconnect=lambda: DeviceClient(MemoryLink(dev), FAST, first_seq=900),
    )
    assert r.active == "new" and r.recovered_from.startswith("info: ")
    assert r.backup_path is None and not (tmp_path / "b.json").exists()
    assert dev.acted["param_set"] == 0

    assert flash_command._finish(r, r.client) == 0
    out = capsys.readouterr().out
    assert "device holds the NEW set" in out and "previous set saved" not in out
    assert "no backup was made" in out


# ----------------------------------------------------------------------------- commit outcome
@pytest.mark.parametrize("stored", [True, False], ids=["stored-new", "stored-nothing"])
def test_commit_answered_outcome_unknown_is_settled_by_reset_and_read_back(tmp_path, stored):
    """SPEC §5: E_OUTCOME_UNKNOWN means either set may be stored; the host resets, reads the
    active set and compares it with the backup and the new blob (on the same link)."""
    dev = FakeDevice(active_blob=OLD, commit_answer=(Status.E_OUTCOME_UNKNOWN, stored))
    c = client_for(dev)
    said: list[str] = []
    if stored:
        r = flash_parameters(c, NEW, 1, tmp_path / "b.json", progress=said.append)
        assert (r.active, r.backup_path, r.client) == ("new", tmp_path / "b.json", c)
        assert r.recovered_from.startswith("param_commit: ") and "E_OUTCOME_UNKNOWN" in (
            r.recovered_from
        )
    else:
        with pytest.raises(
            FlashInterruptedError, match=r"E_OUTCOME_UNKNOWN.*holds its old complete set"
        ) as info:
            flash_parameters(c, NEW, 1, tmp_path / "b.json", progress=said.append)
        e = info.value
        assert (e.active, e.step, e.commit_sent) == ("old", "param_commit", True)
        assert e.backup_path == tmp_path / "b.json" and e.backup_written
    assert dev.resets == 1 and dev.active == (NEW if stored else OLD)
    assert not c.link.closed  # the link was fine: no reconnection, the caller's client kept
    assert any(line.startswith("reset:") for line in said)


@pytest.mark.parametrize(
    "status", [Status.E_CRC, Status.E_STATE, Status.E_FLASH, Status.E_RANGE], ids=lambda s: s.name
)
def test_commit_refusals_that_store_nothing_say_old_without_reset(tmp_path, status):
    """SPEC §5: these answers to a commit mean the previous set is certainly the stored one."""
    dev = FakeDevice(active_blob=OLD, commit_answer=(status, False))
    with pytest.raises(FlashError, match=f"param_commit.*{status.name}.*keeps its old set") as info:
        flash_parameters(client_for(dev), NEW, 1, tmp_path / "b.json")
    e = info.value
    assert (e.active, e.step, e.commit_sent) == ("old", "param_commit", True)
    assert e.backup_path == tmp_path / "b.json" and dev.resets == 0 and dev.flash == OLD


def test_refusal_before_the_commit_says_old_and_whether_a_backup_was_made(tmp_path):
    class Refuses(FakeDevice):
        def _on_param_set(self, f):
            return {"status": Status.E_CONDITION, "crc32": 0}

    with pytest.raises(FlashError, match="param_set.*E_CONDITION.*keeps its old set") as info:
        flash_parameters(client_for(Refuses(active_blob=OLD)), NEW, 1, tmp_path / "b.json")
    e = info.value
    assert (e.active, e.step, e.commit_sent, e.backup_path) == (
        "old",
        "param_set",
        False,
        tmp_path / "b.json",
    )


@pytest.fixture
def fake_over_tcp():
    """serve(device) -> its socket:// URL (the fake behind a TCP socket; stopped at the end)."""
    stops = []

    def serve(dev: FakeDevice) -> str:
        port, stop, thread = serve_tcp(dev)
        stops.append((stop, thread))
        return f"socket://127.0.0.1:{port}"

    yield serve
    for stop, thread in stops:
        stop.set()
        thread.join(5.0)


@pytest.mark.parametrize("stored", [True, False], ids=["stored-new", "stored-nothing"])
def test_cli_says_what_the_library_found_after_outcome_unknown(
    tmp_path, capsys, fake_over_tcp, stored
):
    """magcal flash takes the library's outcome: the new set found is a success (exit 0), the
    old one a failure naming the OLD set and the backup."""
    dev = FakeDevice(active_blob=OLD, commit_answer=(Status.E_OUTCOME_UNKNOWN, stored))
    url = fake_over_tcp(dev)
    result = tmp_path / "r.json"
    write_result(
        result,
        CalibrationResult(
            "ml",
            np.eye(3) * 50.0,
            np.zeros(3),
            field_direction(np.deg2rad(60.0)),
            60.0,
            extra={"mag_unit": "uT"},
        ),
    )
    backup = tmp_path / "b.json"
    capsys.readouterr()
    rc = cli.main(["flash", str(result), "--port", url, "--backup", str(backup)])
    out, err = capsys.readouterr()
    assert dev.resets == 1 and read_backup(backup)["blob"] == OLD
    if stored:
        assert rc == 0, err
        assert "device holds the NEW set" in out and f"previous set saved in {backup}" in out
        assert dev.active != OLD
    else:
        assert rc == 2 and f"device holds the OLD set — backup at {backup}" in err
        assert dev.active == OLD


# ----------------------------------------------------------------------------- one definition
def test_scale_text_is_shared_by_info_and_flash():
    from magcal.commands import common, info

    s = Scale(122, 1, -6, Unit.STANDARD_GRAVITY)
    assert common.scale_text(s) == "122/1 × 10^-6 standard_gravity"
    assert common.scale_text(Scale(1, 6842, 0, Unit.GAUSS)) == "1/6842 gauss"
    assert not hasattr(info, "_scale_text") and not hasattr(flash_command, "_scale_text")


def test_cli_restore_uses_the_librarys_checks_and_default_path(tmp_path, capsys, fake_over_tcp):
    """magcal flash --restore refuses a backup of "no set" with restore's own message, and
    backs the current set up to the library's default path."""
    dev = FakeDevice()
    flash_parameters(client_for(dev), OLD, 1, tmp_path / "none.json")  # records "no set"
    flash_parameters(client_for(dev), NEW, 1, tmp_path / "old.json")  # records OLD
    url = fake_over_tcp(dev)
    capsys.readouterr()
    assert cli.main(["flash", "--restore", str(tmp_path / "none.json"), "--port", url]) == 2
    err = capsys.readouterr().err
    assert "restore: backup" in err and "had no parameter set; there is nothing to write" in err
    assert cli.main(["flash", "--restore", str(tmp_path / "old.json"), "--port", url]) == 0
    (made,) = tmp_path.glob("old.before-restore-*Z.json")
    assert re.fullmatch(r"old\.before-restore-\d{8}T\d{12}Z\.json", made.name)  # µs stamp
    assert read_backup(made)["blob"] == NEW and dev.active == OLD
