"""Session files (``magcal-session: 1`` CSV): the in-memory form, reading and writing.

See ``shared/docs/contracts.md`` for the format.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Session:
    """One recording.

    t   : (N,) float, seconds, strictly increasing
    gyr : (N, 3) float, rad/s, body frame
    acc : (N, 3) float, m/s², specific force, body frame
    mag : (N, 3) float, raw magnetometer units (any unit)
    meta: the ``# key: value`` metadata lines, without ``magcal-session``
    """

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    meta: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t.shape[0])
