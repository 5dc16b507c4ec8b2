"""Tetrahedral meshing of a closed surface with fTetWild (pytetwild).

fTetWild is not reproducible when called in-process: it seeds its random generators from
``std::random_device`` and, besides, a second call in the same process gives another mesh even
with every seed fixed (state left behind by the first call). So every call runs in a fresh
Python child whose ``std::random_device`` is pinned to a constant, which makes the mesh a
function of its inputs (starting the child costs about half a second). The child also works
in a temporary directory, where fTetWild drops its ``__tracked_surface.stl``, so neither the
caller's directory nor its cwd is touched.
"""
from __future__ import annotations

import ctypes
import mmap
import os
import platform
import struct
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

ENVELOPE = 1e-3  # fTetWild's default surface envelope (epsilon), relative to the bounding box diagonal
_SEED = 5489  # what std::random_device returns in the child (mt19937's default seed)
_GETVAL = "_ZNSt13random_device9_M_getvalEv"  # std::random_device::_M_getval()
_stub = None  # executable page holding the replacement; lives as long as the child


def tet_mesh(vertices: np.ndarray, faces: np.ndarray, edge_length: float,
             stop_energy: float = 10.0, coarsen: bool = False,
             envelope: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedralize the closed, outward-oriented triangle surface (vertices, faces).

    ``edge_length`` is fTetWild's ideal edge length in metres (the tet count is not monotonic
    in it); ``stop_energy`` its AMIPS quality target (lower = better tets, slower);
    ``coarsen`` removes every vertex it can while keeping the quality (far fewer tets, the
    same smallest tet, so the same stable time step); ``envelope`` how far the tet mesh's surface
    may stray from the given one, relative to its bounding box diagonal (None: fTetWild's 1e-3). Returns
    (points (n, 3) float64, tets (m, 4) int32) with every tet positively oriented
    (det[x1-x0, x2-x0, x3-x0] > 0), no zero-volume tet and no unreferenced point.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"tet_mesh needs (n, 3) vertices and (m, 3) faces, got "
                         f"{vertices.shape} and {faces.shape}")
    if not edge_length > 0:
        raise ValueError(f"edge_length = {edge_length!r}: must be > 0")
    with tempfile.TemporaryDirectory(prefix="sdexp-tetwild-") as tmp:
        np.savez(Path(tmp) / "in.npz", vertices=vertices, faces=faces,
                 edge_length=float(edge_length), stop_energy=float(stop_energy), coarsen=bool(coarsen),
                 envelope=float(ENVELOPE if envelope is None else envelope))
        # run_path rather than running this file as a script: a script's folder goes first on
        # sys.path, and a module of sdexp/sim could then shadow a standard one in the child.
        code = "import runpy, sys; runpy.run_path(sys.argv[1], run_name='__main__')"
        proc = subprocess.run([sys.executable, "-c", code, str(Path(__file__).resolve())],
                              cwd=tmp, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"fTetWild failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
        with np.load(Path(tmp) / "out.npz") as out:
            points, tets, pinned = out["points"], out["tets"], bool(out["pinned"])
    if not pinned:
        warnings.warn("could not pin std::random_device inside this pytetwild build: the "
                      "tet mesh differs from run to run", RuntimeWarning, stacklevel=2)
    return clean_tets(points, tets)


def clean_tets(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orient every tet positively, drop flat ones and unreferenced points."""
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    d = points[tets[:, 1:]] - points[tets[:, :1]]
    det = np.linalg.det(d)
    solid = np.abs(det) > 1e-12 * np.ptp(points, axis=0).max() ** 3
    tets, det = tets[solid], det[solid]
    tets[det < 0] = tets[det < 0][:, [0, 2, 1, 3]]  # fTetWild emits them negatively oriented
    used, tets = np.unique(tets, return_inverse=True)
    if len(used) == 0:
        raise RuntimeError("fTetWild returned no tetrahedron: is the surface closed?")
    return (np.ascontiguousarray(points[used]),
            np.ascontiguousarray(tets.reshape(-1, 4), dtype=np.int32))


def _got_slots(path: str, symbol: str, landmark: str) -> tuple[list[int], int | None]:
    """Offsets of the relocation slots (GOT entries) through which the ELF shared object at
    ``path`` calls ``symbol``, and the offset of its own symbol ``landmark`` (which gives the
    address the object is loaded at)."""
    data = Path(path).read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:  # 64-bit little-endian only
        return [], None
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", data, 0x3A)
    # (name, type, flags, addr, offset, size, link, info, addralign, entsize)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + k * shentsize)
                for k in range(shnum)]
    sht_rela, sht_dynsym = 4, 11
    dynsym_index = next((k for k, s in enumerate(sections) if s[1] == sht_dynsym), None)
    if dynsym_index is None:
        return [], None
    dynsym, dynstr = sections[dynsym_index], sections[sections[dynsym_index][6]]

    def name(offset: int) -> str:
        start = dynstr[4] + offset
        return data[start:data.index(b"\0", start)].decode()

    symbols = [struct.unpack_from("<IBBHQQ", data, dynsym[4] + 24 * k)
               for k in range(dynsym[5] // 24)]
    names = [name(s[0]) for s in symbols]
    landmark_offset = next((s[4] for n, s in zip(names, symbols) if n == landmark and s[4]), None)
    slots = []
    for s in sections:
        if s[1] == sht_rela and s[6] == dynsym_index:
            for k in range(s[5] // 24):
                r_offset, r_info = struct.unpack_from("<QQ", data, s[4] + 24 * k)
                if names[r_info >> 32] == symbol:
                    slots.append(r_offset)
    return slots, landmark_offset


def _pin_random_device() -> bool:
    """Make std::random_device return _SEED inside fTetWild by pointing its GOT entries at a
    two-instruction function; False where this build or machine does not allow it."""
    global _stub
    from pytetwild import PyfTetWildWrapper

    if platform.machine().lower() not in ("x86_64", "amd64") or os.name != "posix":
        return False
    path, landmark = PyfTetWildWrapper.__file__, "PyInit_PyfTetWildWrapper"
    slots, landmark_offset = _got_slots(path, _GETVAL, landmark)
    if not slots or landmark_offset is None:
        return False
    lib = ctypes.CDLL(path)  # the handle of the already loaded module
    base = ctypes.cast(getattr(lib, landmark), ctypes.c_void_p).value - landmark_offset
    try:
        _stub = mmap.mmap(-1, mmap.PAGESIZE, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    except OSError:  # no writable-and-executable mapping allowed here
        return False
    _stub.write(b"\xb8" + struct.pack("<I", _SEED) + b"\xc3")  # mov eax, _SEED; ret
    target = ctypes.addressof(ctypes.c_char.from_buffer(_stub))
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    for slot in slots:
        page = (base + slot) & ~(mmap.PAGESIZE - 1)
        if libc.mprotect(page, mmap.PAGESIZE, mmap.PROT_READ | mmap.PROT_WRITE) != 0:
            return False
        ctypes.c_void_p.from_address(base + slot).value = target
    return True


def _child_main() -> None:
    import pytetwild

    pinned = _pin_random_device()
    # One thread as a precaution: the order in which parallel passes finish is not pinned.
    with np.load("in.npz") as inp:
        points, tets = pytetwild.tetrahedralize(
            inp["vertices"], inp["faces"], edge_length_abs=float(inp["edge_length"]),
            stop_energy=float(inp["stop_energy"]), coarsen=bool(inp["coarsen"]), num_threads=1,
            epsilon=float(inp["envelope"]),
            quiet=True)
    np.savez("out.npz", points=points, tets=tets, pinned=pinned)


if __name__ == "__main__":
    _child_main()
