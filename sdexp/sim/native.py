"""The compiled 3D force kernel (kernels.c): built with the machine's C compiler on first use,
like numba compiles on first use, and cached under a hash of the source, the flags and the
CPU; written to a temporary name and renamed, so a killed build leaves nothing half-written.

Where no compiler works, the numba reference kernel (same arithmetic, about 3x slower) runs
instead and a warning says so.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

SOURCE = Path(__file__).with_name("kernels.c")
FLAGS = ["-O3", "-march=native", "-mprefer-vector-width=512", "-ffast-math", "-fopenmp",
         "-shared", "-fPIC"]
_P, _D, _I = ctypes.c_void_p, ctypes.c_double, ctypes.c_int64
SIGNATURE = ctypes.CFUNCTYPE(ctypes.c_int, _P, _P, _P, _P, _D, _D, _P, _P, _I, _I, _I)  # see kernels.c


def _cpu_id() -> str:
    try:
        flags = [line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags")]
        return flags[0] if flags else platform.processor()
    except OSError:
        return platform.processor()


def _library_path(cache_dir: Path) -> Path:
    h = hashlib.sha256(SOURCE.read_bytes() + " ".join(FLAGS).encode() + _cpu_id().encode())
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
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def default_cache_dir() -> Path:
    return Path(os.environ.get("SDEXP_CACHE", Path.home() / ".cache" / "sdexp")).expanduser()


@lru_cache(maxsize=None)
def corotated_kernel_3d():
    """A ctypes function with the C signature of kernels.c (compiled, or the numba cfunc)."""
    path = _library_path(default_cache_dir())
    try:
        if not path.exists():
            _build(path)
        fn = ctypes.CDLL(str(path)).corotated_forces_3d
        fn.restype, fn.argtypes = SIGNATURE._restype_, list(SIGNATURE._argtypes_)
        return fn
    except (OSError, subprocess.CalledProcessError) as err:
        detail = getattr(err, "stderr", "") or str(err)
        warnings.warn(f"sdexp: compiled FEM kernel unavailable ({detail.strip()[:200]}); "
                      "using the numba kernel, about 3x slower", RuntimeWarning, stacklevel=2)
        from sdexp.sim.fem import corotated_cfunc_3d
        return corotated_cfunc_3d.ctypes
