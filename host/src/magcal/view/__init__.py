# SPDX-License-Identifier: Apache-2.0
"""``magcal collect --view``: a live page of the collection in the browser.

:mod:`magcal.view.model` turns the recorders' progress reports
(:class:`magcal.device.collect.CollectProgress`) into what the page draws, one panel per
compass; :mod:`magcal.view.server` serves the page on 127.0.0.1 and pushes each new state to
it over a WebSocket; ``static/`` holds the page (plain HTML and canvas code, no third-party
script, nothing fetched from the network).
"""
