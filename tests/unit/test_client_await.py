# SPDX-License-Identifier: Apache-2.0
"""DeviceClient's wait for one attempt's response raises on a time-out (never returns None),
and a request retries such attempts then raises DeviceTimeoutError naming them all."""

from __future__ import annotations

import pytest

from magcal.device.client import ClientConfig, DeviceClient, DeviceTimeoutError
from magcal.device.generated import MessageId, Status
from magcal.link import LinkTimeoutError


class SilentLink:
    """A link to a device that never answers."""

    url = "socket://silent:1"

    def __init__(self) -> None:
        self.writes: list[bytes] = []

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        self.writes.append(data)

    def read(self, timeout_s: float, max_bytes: int = 4096) -> bytes:
        raise LinkTimeoutError(f"read {self.url}: no byte within {timeout_s} s", self.url)

    def close(self) -> None:
        pass


def test_await_raises_on_a_time_out():
    c = DeviceClient(SilentLink(), ClientConfig(request_timeout_s=0.01))
    with pytest.raises(
        DeviceTimeoutError, match=r"hello on socket://silent:1: no response within"
    ) as info:
        c._await(MessageId.HELLO, MessageId.HELLO_RESP, 7, 0.01, "hello")
    assert info.value.status == Status.E_EMPTY and info.value.op == "hello"


def test_a_request_retries_then_raises():
    link = SilentLink()
    c = DeviceClient(link, ClientConfig(request_timeout_s=0.01, request_retries=2))
    with pytest.raises(
        DeviceTimeoutError, match=r"hello on socket://silent:1: no response after 3 attempts"
    ):
        c.hello()
    assert len(link.writes) == 3 and len(set(link.writes)) == 1  # the same bytes each time
    assert c.stats.retries == 2
