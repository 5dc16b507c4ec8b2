"""The compiled kernels (kernels.c): built with the machine's C compiler on first use, like
numba compiles on first use, and cached under a hash of the source, the flags and the CPU;
written to a temporary name and renamed, so a killed build leaves nothing half-written, and
checked against the digest recorded at build time before it is loaded (a damaged one is rebuilt).

Where no compiler works (``library()`` is None), the numba references (same arithmetic, about
3x slower) run instead and a warning says so: sdexp.sim.physics.fem.kernels, the one place that
chooses, and the integrator's Body go by that; otherwise an INFO line names the compiled library. The two
agree to 1e-10 (tests/sim/test_fem.py: test_compiled_step_matches_the_numba_reference).
"""
from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("kernels.c")
HEADERS = (Path(__file__).with_name("forces.h"),)   # included by kernels.c: part of the build's hash
FLAGS = ["-O3", "-march=native", "-mprefer-vector-width=512", "-ffast-math", "-fopenmp",
         "-shared", "-fPIC"]
_P, _D, _I = ctypes.c_void_p, ctypes.c_double, ctypes.c_int64
SIGNATURE = ctypes.CFUNCTYPE(ctypes.c_int, _P, _P, _P, _P, _D, _D, _P, _P, _I, _I, _I)  # see kernels.c


class Step(ctypes.Structure):
    """kernels.c's Step: one body and one control step of it (pointers into its arrays)."""
    _fields_ = ([(n, _I) for n in ("dim", "nv", "ne", "nt", "n_sub", "n_rotors", "n_boxes", "nodes",
                                   "single")]
                + [(n, _D) for n in ("dt", "mu", "lam", "damping", "deform_damping", "gravity",
                                     "ground", "friction")]
                + [(n, _P) for n in ("x", "v", "q", "fbuf", "ext", "dirs", "fext", "minv", "mass",
                                     "Bm", "vol", "boxes_min", "boxes_max", "weights", "thrust",
                                     "gravity_share", "el", "face_ptr", "faces", "vert_ptr", "verts")])


def _cpu_id() -> str:
    try:
        flags = [line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags")]
        return flags[0] if flags else platform.processor()
    except OSError:
        return platform.processor()


def _library_path(cache_dir: Path) -> Path:
    text = SOURCE.read_bytes() + b"".join(h.read_bytes() for h in HEADERS)
    h = hashlib.sha256(text + " ".join(FLAGS).encode() + _cpu_id().encode())
    return cache_dir / f"kernels-{h.hexdigest()[:16]}.so"


def _build(target: Path) -> None:
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        raise OSError("no C compiler on PATH")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".so.tmp")
    os.close(fd)
    try:
        subprocess.run([cc, *FLAGS, "-o", tmp, str(SOURCE), "-lm"], check=True, capture_output=True, text=True)
        digest = _digest(Path(tmp))
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    from sdexp.cache import atomic_write
    atomic_write(_digest_path(target), lambda p: p.write_text(digest))


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _digest_path(library_path: Path) -> Path:
    return library_path.with_suffix(".sha256")


def _intact(path: Path) -> bool:
    """The library is whole: its bytes hash to what the build recorded. A truncated or
    overwritten shared library can kill the process with a bus error when loaded, so it is
    checked before, not after."""
    try:
        return path.exists() and _digest_path(path).read_text().strip() == _digest(path)
    except OSError:
        return False


def default_cache_dir() -> Path:
    return Path(os.environ.get("SDEXP_CACHE", Path.home() / ".cache" / "sdexp")).expanduser()


@lru_cache(maxsize=None)
def library():
    """The compiled kernels.c, or None (with a warning) where it cannot be built."""
    path = _library_path(default_cache_dir())
    try:
        if not _intact(path):   # missing, damaged, or built before the digest was recorded
            _build(path)
        lib = ctypes.CDLL(str(path))
    except (OSError, subprocess.CalledProcessError) as err:
        detail = getattr(err, "stderr", "") or str(err)
        warnings.warn(f"sdexp: compiled FEM kernels unavailable ({detail.strip()[:200]}); "
                      "using the numba ones, about 3x slower", RuntimeWarning, stacklevel=2)
        return None
    for name in ("corotated_forces_3d", "corotated_forces_3d_f32"):   # float64 / float32 forces
        getattr(lib, name).restype = SIGNATURE._restype_
        getattr(lib, name).argtypes = list(SIGNATURE._argtypes_)
    lib.advance.restype = ctypes.c_int
    lib.advance.argtypes = [ctypes.POINTER(Step), ctypes.POINTER(ctypes.c_double)]
    lib.block_size.restype = ctypes.c_int
    lib.forces_only.restype = ctypes.c_int
    lib.forces_only.argtypes = [ctypes.POINTER(Step), ctypes.c_int64]
    for name in ("fma_probe", "fma_probe_f32"):   # the benchmark's peak probe
        getattr(lib, name).restype = ctypes.c_double
        getattr(lib, name).argtypes = [ctypes.c_int64, ctypes.c_double]
    lib.fma_probe_width.restype = ctypes.c_int
    lib.fma_probe_width.argtypes = [ctypes.c_int]
    # once per process (library() is cached): the run's log says which kernels stepped it
    log.info(f"sdexp: FEM kernels: compiled C ({path})")
    return lib


def blocked(rows, block: int, pad=0.0):
    """(n, ...) element rows in kernels.c's blocked layout (ceil(n / block), ..., block), the last
    block padded with ``pad`` (a value, or a row)."""
    rows = np.asarray(rows)
    n = len(rows)
    nb = -(-n // block)
    out = np.empty((nb * block,) + rows.shape[1:], rows.dtype)
    out[:n] = rows
    out[n:] = pad
    return np.ascontiguousarray(np.moveaxis(out.reshape((nb, block) + rows.shape[1:]), 1, -1))
