# SPDX-License-Identifier: Apache-2.0
"""SPEC §5's flash flow (protocol/SPEC.md) on top of :class:`DeviceClient`.

:func:`flash_parameters` writes a parameter set with a backup of the device's current set
saved first and every step read back bit for bit; after a link failure it finds out which
complete set the device holds (:class:`FlashInterruptedError` says "old", "new" or
"unknown"). :func:`restore` writes a backup back; :func:`read_backup` reads and checks one.

Example::

    with open_link("socket://127.0.0.1:5760") as link:
        client = DeviceClient(link)
        result = flash_parameters(client, blob, fixed_point.FORMAT_VERSION, "backup.json")
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import secrets
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from magcal.device.client import (
    DeviceClient,
    DeviceError,
    DeviceInfo,
    DeviceTimeoutError,
    ParamSet,
    ParamWhich,
)
from magcal.device.framing import crc32_iso_hdlc
from magcal.device.generated import Status
from magcal.errors import MagcalError
from magcal.link.base import LinkClosedError, LinkError

log = logging.getLogger(__name__)

BACKUP_FORMAT = "magcal-param-backup/1"
#: What os.link raises on a file system without hard links.
_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS}


class FlashError(MagcalError):
    """flash_parameters or restore failed. Where the device stands:

    active      : the complete set it holds: "old" (nothing was stored: refused or failed
                  before the commit, a commit refusal that stores nothing, or read back),
                  "new", or "unknown" (it could not be found out, or is neither)
    step        : the step that failed ("" before the flow's steps)
    commit_sent : whether param_commit was sent
    backup_path : the backup of the previous set, None when none was written
    """

    def __init__(
        self,
        message: str,
        active: str = "old",
        step: str = "",
        *,
        commit_sent: bool = False,
        backup_path: Path | None = None,
    ) -> None:
        super().__init__(message)
        self.active = active
        self.step = step
        self.commit_sent = commit_sent
        self.backup_path = backup_path

    @property
    def backup_written(self) -> bool:
        return self.backup_path is not None


class FlashInterruptedError(FlashError):
    """The flow was interrupted, by a link failure or by a commit whose outcome the device
    could not tell (E_OUTCOME_UNKNOWN), and the host then tried to find out which complete set
    the device holds: ``active`` "old" (found, or no commit was sent) or "unknown" (it could
    not be asked, or holds neither); a device found holding the new set is a FlashResult."""


Reconnect = Callable[[], DeviceClient]
#: Told each step as it starts or ends, in words ("param_set: writing the new set"); for a
#: command line's progress lines. Must not raise.
Progress = Callable[[str], None]


def _no_progress(_: str) -> None:
    pass


@dataclass(frozen=True)
class FlashResult:
    """The outcome of a completed flash: the new set is active (read back bit-exact).

    active        : "new"
    crc32         : the set's CRC-32/ISO-HDLC
    backup_path   : where the previous set was saved; None when no backup was written (a
                    link failure came before the backup step and the recovery found the new
                    set already active: nothing was written)
    recovered_from: the link failure the flow recovered from ("" when none)
    client        : the client to go on with (a reconnected one after a recovery)
    """

    active: str
    crc32: int
    backup_path: Path | None
    recovered_from: str = ""
    client: DeviceClient | None = field(default=None, compare=False, repr=False)


def _read_active(client: DeviceClient) -> ParamSet | None:
    """The active set, or None when the device has none (E_NO_PARAMS)."""
    try:
        return client.param_get(ParamWhich.ACTIVE)
    except DeviceError as exc:
        if exc.status == Status.E_NO_PARAMS and not isinstance(exc, DeviceTimeoutError):
            return None
        raise


def _write_backup(
    path: Path, old: ParamSet | None, info: DeviceInfo, url: str, overwrite: bool
) -> None:
    """Save the device's current set atomically: a temporary file in the same directory,
    fsync, then a hard link to ``path``, which fails when ``path`` exists (an existing file is
    never replaced, even one created meanwhile), or a rename when ``overwrite``. The temporary
    file is removed whatever happens."""
    doc = {
        "format": BACKUP_FORMAT,
        "format_version": None if old is None else old.format_version,
        "blob": None if old is None else old.blob.hex(),
        "crc32": None if old is None else old.crc32,
        "device_uid": info.uid_hex,
        "fw_version": info.fw_version_str,
        "fw_build": f"{info.fw_build:08x}",
        "port": url,
        "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    tmp: Path | None = None
    try:
        # A name nobody else uses ("x": never an existing file); the umask sets its mode.
        name = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
        fh = open(name, "x", encoding="utf-8")
        tmp = name
        with fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, path)
            tmp = None
        else:
            _link_new(tmp, path)
    except FileExistsError as exc:
        raise FlashError(
            f"flash: backup file {path} exists; nothing was written to the device: give "
            "another backup path (an earlier backup is worth keeping) or allow overwriting"
        ) from exc
    except OSError as exc:
        raise FlashError(
            f"flash: cannot save the backup to {path} ({exc.strerror or exc}); nothing was "
            "written to the device: choose a writable backup path"
        ) from exc
    finally:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


def _link_new(tmp: Path, path: Path) -> None:
    """Make ``path`` a copy of the complete file ``tmp``; FileExistsError when ``path`` exists."""
    try:
        os.link(tmp, path)
    except OSError as exc:
        if exc.errno not in _NO_HARD_LINKS:
            raise
        # A file system without hard links (FAT): copy into a file only this call creates.
        with open(tmp, "rb") as src, open(path, "xb") as dst:
            try:
                shutil.copyfileobj(src, dst)
                dst.flush()
                os.fsync(dst.fileno())
            except BaseException:
                os.unlink(path)  # ours, and incomplete
                raise


def read_backup(path: str | os.PathLike) -> dict[str, Any]:
    """A backup written by flash_parameters, checked (format, hex blob, CRC-32)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise FlashError(f"restore: cannot read backup {p} ({exc}); check the path") from exc
    if not isinstance(doc, dict) or doc.get("format") != BACKUP_FORMAT:
        raise FlashError(f"restore: {p} is not a {BACKUP_FORMAT} backup; check the file")
    if doc.get("blob") is not None:
        try:
            blob = bytes.fromhex(doc["blob"])
        except (TypeError, ValueError) as exc:
            raise FlashError(
                f"restore: backup {p} has a malformed blob; the file is damaged"
            ) from exc
        if crc32_iso_hdlc(blob) != doc.get("crc32"):
            raise FlashError(
                f"restore: backup {p}'s blob does not match its CRC-32; the file is damaged: "
                "do not write it"
            )
        doc["blob"] = blob
    return doc


def _hello_after_reset(client: DeviceClient, reconnect: Reconnect | None) -> DeviceClient:
    """hello until the restarted device answers (reconnecting when the link dropped). A client
    made here is closed when this raises; ``client`` is closed when replaced."""
    deadline = time.monotonic() + client.config.reset_recovery_timeout_s
    given = client
    attempt = 0
    try:
        while True:
            attempt += 1
            try:
                client.hello()
                return client
            except (LinkError, DeviceTimeoutError) as exc:
                if time.monotonic() >= deadline:
                    raise
                log.info(
                    "hello after reset on %s: attempt %d failed (%s)", client.url, attempt, exc
                )
                if isinstance(exc, LinkError) and reconnect is not None:
                    client.close()
                    try:
                        client = reconnect()
                    except LinkError as exc2:
                        log.info("reconnect after reset failed (%s)", exc2)
                        if time.monotonic() >= deadline:
                            raise
                        time.sleep(0.1)
                elif isinstance(exc, LinkClosedError):
                    raise
    except BaseException:
        if client is not given:
            client.close()
        raise


def _same(p: ParamSet | None, blob: bytes | None, format_version: int | None) -> bool:
    if p is None or blob is None:
        return p is None and blob is None
    return p.blob == blob and p.format_version == format_version


#: Answers to param_commit after which the previous set is certainly the stored one (SPEC §5).
_COMMIT_STORED_NOTHING = {Status.E_CRC, Status.E_STATE, Status.E_FLASH, Status.E_RANGE}


@dataclass
class _Flow:
    """Where a flash_parameters call is: for its messages, errors and recovery."""

    url: str
    blob: bytes
    format_version: int
    path: Path
    say: Progress
    step: str = "hello"
    old: ParamSet | None = None
    backup_written: bool = False
    commit_sent: bool = False

    @property
    def crc(self) -> int:
        return crc32_iso_hdlc(self.blob)

    @property
    def backup(self) -> Path | None:
        return self.path if self.backup_written else None

    def error(self, message: str, active: str = "old", cls: type[FlashError] = FlashError):
        return cls(
            message,
            active,
            self.step,
            commit_sent=self.commit_sent,
            backup_path=self.backup,
        )


def flash_parameters(
    client: DeviceClient,
    blob: bytes,
    format_version: int,
    backup_path: str | os.PathLike,
    *,
    reconnect: Reconnect | None = None,
    overwrite_backup: bool = False,
    progress: Progress | None = None,
) -> FlashResult:
    """Write a parameter set with SPEC §5's flow, every step checked:

    hello (when not done) and info (format version and size must match) -> param_get(active)
    -> backup file saved (before anything is written) -> param_set -> param_get(staged)
    compared bit for bit -> param_commit(crc32) -> reset -> hello -> param_get(active)
    compared bit for bit with ``blob``.

    reconnect : makes a new client on a fresh link (used after a reset that dropped the link,
        and after a link failure to find out what the device holds)
    progress : called with a line of text at each step (nothing when None)

    Returns FlashResult(active="new"), also when the flow was interrupted and the device was
    then found to hold the new set. Interrupted means a link failure, or a commit answered
    E_OUTCOME_UNKNOWN (either set may be stored; SPEC §5) or a refusal after the commit: the
    device is then reset (when the commit was sent) and its active set compared with the backup
    and with ``blob``, on the same client when its link works, else on a reconnected one.
    Raises FlashInterruptedError with ``active`` "old" or "unknown" when that finds the old set
    or cannot tell; FlashError with ``active`` "old" when the device refused a step before the
    commit or refused the commit with E_CRC, E_STATE, E_FLASH or E_RANGE (nothing stored), or
    before anything was written (backup, format checks); FlashError when a read-back differs
    (``active`` says which set is in use). Every error also says whether the commit was sent
    and where the backup is (``backup_path``; None: none was written)."""
    flow = _Flow(
        client.url, bytes(blob), format_version, Path(backup_path), progress or _no_progress
    )
    blob, crc, path, say = flow.blob, flow.crc, flow.path, flow.say
    given = client
    try:
        if client.version is None:
            client.hello()
        flow.step = "info"
        info = client.info()
        if info.params_format_version != format_version or info.params_size != len(blob):
            raise flow.error(
                f"flash on {client.url}: the device takes parameter format "
                f"{info.params_format_version} of {info.params_size} bytes; this set is format "
                f"{format_version} of {len(blob)} bytes; nothing was written: convert the "
                "calibration for this firmware"
            )
        flow.step = "param_get(active)"
        flow.old = old = _read_active(client)
        say(
            "param_get(active): the current set is "
            + ("none (the device has no set)" if old is None else f"CRC-32 0x{old.crc32:08x}")
        )
        flow.step = "backup"
        _write_backup(path, old, info, client.url, overwrite_backup)
        flow.backup_written = True
        log.info("flash on %s: previous set saved to %s", client.url, path)
        say(f"backup: the current set saved to {path}")
        flow.step = "param_set"
        say(f"param_set: staging the new set ({len(blob)} bytes, CRC-32 0x{crc:08x})")
        client.param_set(format_version, blob)
        flow.step = "param_get(staged)"
        staged = client.param_get(ParamWhich.STAGED)
        if not _same(staged, blob, format_version) or staged.crc32 != crc:
            raise flow.error(
                f"flash on {client.url}: the staged set read back differs from the one sent "
                "(nothing committed; the device keeps its old set): check the link and retry"
            )
        say("param_get(staged): read back, equal bit for bit")
        flow.step = "param_commit"
        flow.commit_sent = True
        say(f"param_commit: storing CRC-32 0x{crc:08x}")
        try:
            client.param_commit(crc)
        except DeviceError as exc:
            if isinstance(exc, DeviceTimeoutError) or exc.status not in _COMMIT_STORED_NOTHING:
                raise
            raise flow.error(
                f"flash on {client.url}: {exc}; the device stored nothing and keeps its old set "
                "(SPEC §5): run flash again"
            ) from exc
        flow.step = "reset"
        say("reset: restarting the device")
        client.reset()
        flow.step = "hello after reset"
        client = _hello_after_reset(client, reconnect)
        say("hello: the device answers again after the reset")
        flow.step = "param_get(active) after reset"
        active = _read_active(client)
        if not _same(active, blob, format_version):
            which = (
                "its old set"
                if _same(active, old.blob if old else None, old.format_version if old else None)
                else "another set"
            )
            raise flow.error(
                f"flash on {client.url}: after commit and reset the device uses {which}, not "
                f"the new one (CRC-32 0x{crc:08x}); the commit did not take effect: run flash "
                f"again, and restore {path} if needed",
                "old" if which == "its old set" else "unknown",
            )
    except (LinkError, DeviceTimeoutError) as exc:
        return _find_out(client, given, exc, flow, reconnect, link_ok=False)
    except DeviceError as exc:
        if not flow.commit_sent:
            raise flow.error(
                f"flash on {client.url}: {exc}; nothing was committed, so the device keeps its "
                "old set"
            ) from exc
        # E_OUTCOME_UNKNOWN (or an answer SPEC §5 does not give a commit, or a refusal after
        # a stored commit): either set may be the stored one, and the link works.
        return _find_out(client, given, exc, flow, reconnect, link_ok=True)
    except BaseException:
        if client is not given:
            client.close()  # made by reconnect after the reset
        raise
    log.info("flash on %s: new set active (CRC-32 0x%08x), verified bit for bit", client.url, crc)
    say("param_get(active) after reset: the new set, equal bit for bit")
    return FlashResult("new", crc, path, "", client)


def _find_out(
    client: DeviceClient,
    given: DeviceClient,
    exc: Exception,
    flow: _Flow,
    reconnect: Reconnect | None,
    link_ok: bool,
) -> FlashResult:
    """After ``exc`` at ``flow.step``: find which complete set the device holds, on ``client``
    when its link works (``link_ok``), else on a reconnected one. After a commit the device is
    reset first (a stored set becomes active at the next reset). Clients made here are closed
    unless returned; ``given`` (the caller's) is closed only when its link failed."""
    url, step, commit_sent = flow.url, flow.step, flow.commit_sent
    if link_ok:
        prefix = f"flash on {url}: {step} left open which set is stored ({exc})"
    else:
        prefix = f"flash on {url}: link failure at {step} ({exc})"
    log.warning("%s; finding out what the device holds", prefix)
    if not link_ok:
        client.close()
        if reconnect is None:
            if not commit_sent:
                raise flow.error(
                    f"{prefix}; the commit was never sent, so the device holds its old "
                    "complete set: reconnect and run flash again",
                    "old",
                    FlashInterruptedError,
                ) from exc
            raise flow.error(
                f"{prefix}; the commit was sent, so the device holds either its old or the new "
                "complete set (a commit is atomic): reconnect, read the active set (magcal "
                "verify) and flash again if it is the old one",
                "unknown",
                FlashInterruptedError,
            ) from exc
    fresh: DeviceClient | None = client if link_ok else None

    def close_ours() -> None:
        if fresh is not None and fresh is not given:
            fresh.close()  # a one-client device (the SIL) would refuse the next connection

    try:
        if fresh is None:
            flow.say(f"link failure at {step}: reconnecting to find out which set the device holds")
            fresh = reconnect()
        if fresh.version is None:
            fresh.hello()
        if commit_sent:
            # A committed set becomes active at the next reset: restart to find out.
            flow.say("reset: the commit may have been stored; restarting to find out")
            fresh.reset()
            fresh = _hello_after_reset(fresh, reconnect)
        active = _read_active(fresh)
    except BaseException as exc2:
        close_ours()
        if not isinstance(exc2, (LinkError, DeviceError)):
            raise
        holds = (
            "either its old or the new complete set"
            if commit_sent
            else "its old complete set (the commit was never sent)"
        )
        again = "reconnecting" if not link_ok else "resetting and reading it back"
        raise flow.error(
            f"{prefix}; {again} failed too ({exc2}); the device holds {holds}: check the "
            "link, then read the active set (magcal verify) and flash again if needed",
            "unknown" if commit_sent else "old",
            FlashInterruptedError,
        ) from exc
    if _same(active, flow.blob, flow.format_version):
        log.warning("flash on %s: recovered; the device holds the new set (verified)", url)
        flow.say("param_get(active): the new set, equal bit for bit")
        return FlashResult("new", flow.crc, flow.backup, f"{step}: {exc}", fresh)
    close_ours()
    old = flow.old
    # Without a commit nothing was stored: whatever is active is the set from before.
    if not commit_sent or _same(
        active, old.blob if old else None, old.format_version if old else None
    ):
        raise flow.error(
            f"{prefix}; found out: the device holds its old complete set (verified bit for "
            "bit): run flash again",
            "old",
            FlashInterruptedError,
        ) from exc
    raise flow.error(
        f"{prefix}; found out: the device's active set is neither the old nor the new one: "
        f"restore {flow.path} or flash again",
        "unknown",
        FlashInterruptedError,
    ) from exc


def restorable_backup(path: str | os.PathLike) -> dict[str, Any]:
    """read_backup, refusing a backup that records no set (there is nothing to write back)."""
    doc = read_backup(path)
    if doc.get("blob") is None:
        raise FlashError(
            f"restore: backup {path} records that the device had no parameter set; there is "
            "nothing to write back (the protocol has no erase)"
        )
    return doc


def before_restore_path(backup_path: str | os.PathLike) -> Path:
    """Where restore saves the set it replaces, by default:
    ``<backup>.before-restore-<UTC time, µs>.json`` next to the backup."""
    p = Path(backup_path)
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
    return p.with_name(f"{p.stem}.before-restore-{stamp}.json")


def restore(
    client: DeviceClient,
    backup_path: str | os.PathLike,
    *,
    new_backup_path: str | os.PathLike | None = None,
    reconnect: Reconnect | None = None,
    force: bool = False,
    progress: Progress | None = None,
) -> FlashResult:
    """Write a backup back with :func:`flash_parameters` (the current set is backed up first,
    to ``new_backup_path``, default :func:`before_restore_path`). Refuses a backup that records
    no set, and one of another device (its uid) unless force."""
    p = Path(backup_path)
    doc = restorable_backup(p)
    try:
        if client.version is None:
            client.hello()
        info = client.info()
    except (LinkError, DeviceError) as exc:
        raise FlashError(f"restore: {exc}; nothing was written", "old", "info") from exc
    if doc.get("device_uid") != info.uid_hex and not force:
        raise FlashError(
            f"restore: backup {p} is of device {doc.get('device_uid')}, this is device "
            f"{info.uid_hex}; nothing was written: use that device's backup (or force)"
        )
    return flash_parameters(
        client,
        doc["blob"],
        int(doc["format_version"]),
        before_restore_path(p) if new_backup_path is None else new_backup_path,
        reconnect=reconnect,
        progress=progress,
    )
