"""The simulator: meshes, FEM physics, the drone assembler, sensors, rigid-body analysis."""
from sdexp import numba_cache

numba_cache.install()   # numba's disk cache, safe for parallel workers (see there)
