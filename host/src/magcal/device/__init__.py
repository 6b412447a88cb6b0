# SPDX-License-Identifier: Apache-2.0
"""Our firmware's side of the host: the protocol codec (generated from protocol/schema.json),
the device's fixed-point parameter format, and the device commands (info, collect, flash,
verify)."""
