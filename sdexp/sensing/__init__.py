"""The observation interface between the simulator and the learning/control side.

``SensorLayout``, ``Readings``, the decomposed ``State`` and ``decompose`` (sdexp.sensing.state)
and the rotation conventions they use (sdexp.sensing.rotations). sdexp.model, sdexp.control and
sdexp.discrepancy import only this from the simulator side, except where the import-linter
contract in pyproject.toml names an exception.
"""
from sdexp import numba_cache

numba_cache.install()   # before any of the cached numba functions below is first called

from sdexp.sensing.state import Readings, SensorLayout, State, decompose  # noqa: E402

__all__ = ["Readings", "SensorLayout", "State", "decompose"]
