"""The world simulator for the SIL now lives in the package: :mod:`magcal.sim.world`. This
module re-exports it for older imports."""

from magcal.sim.world import *  # noqa: F403
from magcal.sim.world import __all__  # noqa: F401
