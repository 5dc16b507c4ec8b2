"""A drone's body from a mesh file (``drone.mesh.file``): read, scaled, checked, oriented.

3D: a closed triangle surface (quads are split) that fTetWild will tetrahedralise, or a volume
mesh of tetrahedra, used as given. 2D: a closed outline, either the line cells of a mesh file,
the boundary of a triangle mesh (re-meshed by Triangle, so ``drone.mesh.edge_length`` holds), or
a text file of "x y" rows. Everything meshio reads is accepted; the checks say in one line what
is wrong with a file that is not one solid body (empty, unreadable, NaN vertices, flat, open,
non-manifold, self-intersecting, several bodies), since fTetWild would otherwise mesh it into
something else without a word. They run where the file is read, before anything is meshed or
written: the run's preflight reads it (sdexp.sim.checks).
"""
from __future__ import annotations

import functools
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from sdexp.config import mesh_path, mesh_path_candidates
from sdexp.errors import UserError, one_line
from sdexp.sim.mesh.surface import boundary_faces, enclosed_volume
from sdexp.sim.mesh.topology import crossing_pairs, pieces, pinched_vertices

FORMATS = "STL, OBJ, PLY, OFF, VTK/VTU, Gmsh .msh (anything meshio reads)"
TEXT_SUFFIXES = (".txt", ".csv", ".xy", ".dat")   # 2D: a closed polyline, one "x y" row per vertex
KEY = "drone.mesh.file"
log = logging.getLogger(__name__)


@dataclass
class Body:
    dim: int
    vertices: np.ndarray           # (n, dim), scaled to metres
    faces: np.ndarray              # 3D: (m, 3) outward triangles; 2D: (m, 2) segments, body on the left
    holes: np.ndarray              # 2D: (k, 2) one point inside each hole; 3D: (0, 3)
    elems: Optional[np.ndarray]    # a volume mesh given as such (tets), on ``vertices``; else None

    @property
    def extent(self) -> np.ndarray:
        return np.ptp(self.vertices, axis=0)


def resolve(path: str) -> Path:
    """The file ``drone.mesh.file = path`` names (sdexp.config.mesh_path says where it is looked for)."""
    found = mesh_path(path)
    folder = next((p for p in mesh_path_candidates(path) if p.is_dir()), None)
    if found is None and folder is not None:
        raise UserError(f"{KEY} = {path!r} is a folder ({folder}), not a file: give the mesh file itself, "
                        f"in {FORMATS}")
    if found is None:
        where = ", ".join(str(p.parent) for p in mesh_path_candidates(path))
        raise UserError(f"{KEY} = {path!r}: no such file (looked in {where}); give a mesh in {FORMATS}")
    return found


def read_body(path: str, dim: int, scale: float) -> Body:
    """The body of the file at ``path`` (resolved as :func:`resolve` says) times ``scale``."""
    p = resolve(path)
    try:   # meshio reads an empty file as an IndexError, an unreadable one as whatever it meets
        with open(p, "rb") as fh:
            empty = not fh.read(1)
    except OSError as err:
        raise UserError(f"{KEY} = {p.name}: cannot read it ({err.strerror or err}): "
                        f"make it readable ({p})") from None
    if empty:
        raise UserError(f"{KEY} = {p.name}: the file is empty (0 bytes): export the mesh again ({p})")
    return _read(str(p), p.stat().st_mtime_ns, int(dim), float(scale))


@functools.lru_cache(maxsize=8)   # validate() and the drone builder read the same file
def _read(path: str, mtime: int, dim: int, scale: float) -> Body:
    name = Path(path).name
    if dim == 2 and Path(path).suffix.lower() in TEXT_SUFFIXES:
        try:
            ring = np.loadtxt(path, delimiter="," if path.lower().endswith(".csv") else None, ndmin=2)[:, :2]
        except (ValueError, IndexError, OSError) as err:
            raise UserError(f"{KEY} = {name}: cannot read it as 'x y' rows ({one_line(err)})") from None
        if len(ring) > 1 and np.allclose(ring[0], ring[-1]):
            ring = ring[:-1]
        _finite(name, ring)
        k = np.arange(len(ring))
        return _outline(name, ring * scale, np.c_[k, (k + 1) % len(k)])
    import meshio
    try:
        with warnings.catch_warnings():   # meshio's binary-STL size test overflows on an ASCII STL, harmlessly
            warnings.simplefilter("ignore", RuntimeWarning)
            mesh = meshio.read(path)
    except Exception as err:   # meshio raises many kinds (ReadError, ValueError, KeyError, ...)
        raise UserError(f"{KEY} = {name}: cannot read it ({one_line(err)}); give a mesh in {FORMATS}"
                        + (f" or 'x y' rows ({', '.join(TEXT_SUFFIXES)})" if dim == 2 else "")) from None
    cells = {}
    for block in mesh.cells:
        cells.setdefault(block.type, []).append(np.asarray(block.data, dtype=np.int64))
    cells = {k: np.vstack(v) for k, v in cells.items()}
    points = np.asarray(mesh.points, dtype=np.float64) * scale
    _finite(name, points)
    if dim == 3:
        return _body3(name, points, cells)
    return _body2(name, points, cells)


def _finite(name: str, points: np.ndarray) -> None:
    if len(points) == 0:
        raise UserError(f"{KEY} = {name}: holds no vertices: export the mesh again")
    bad = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if len(bad):
        raise UserError(f"{KEY} = {name}: {len(bad)} of its {len(points)} vertices are NaN or infinite "
                        f"(vertex {bad[0]}: {points[bad[0]].tolist()}): export the mesh again")


def _body3(name: str, points: np.ndarray, cells: dict) -> Body:
    if points.shape[1] != 3:
        raise UserError(f"{KEY} = {name}: its points are {points.shape[1]}D; a 3D drone needs x, y, z")
    if "tetra" in cells:
        from sdexp.sim.mesh.tetmesh import clean_tets
        try:
            pts, tets = clean_tets(points, cells["tetra"])
        except RuntimeError:
            raise UserError(f"{KEY} = {name}: its tetrahedra enclose zero volume") from None
        faces = boundary_faces(tets)
        _one_piece(name, pts, faces)
        return Body(3, pts, faces, np.zeros((0, 3)), tets)
    tris = [cells[k] for k in ("triangle",) if k in cells]
    if "quad" in cells:
        q = cells["quad"]
        tris.append(np.r_[q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    if not tris:
        raise UserError(f"{KEY} = {name}: holds no triangles, quads or tetrahedra (cells: "
                        f"{', '.join(cells) or 'none'}); a 3D drone needs a closed surface or a tet mesh")
    pts, faces = _merge(points, np.vstack(tris))
    _solid(name, pts, faces)
    if enclosed_volume(pts, faces) < 0:   # inward-facing (a CAD export's usual slip): turned outward, not refused
        log.info(f"{KEY} = {name}: its triangles face inward (negative volume): turned outward")
        faces = faces[:, [0, 2, 1]]
    return Body(3, pts, faces, np.zeros((0, 3)), None)


def _solid(name: str, pts: np.ndarray, faces: np.ndarray) -> None:
    """A surface bounds one solid, or the first thing wrong with it, in one line. Zero volume is
    checked first: a flat closed box has its edges in threes and fours, "not closed" would mislead."""
    spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False) if len(pts) >= 3 else np.zeros(3)
    if len(faces) == 0 or spread[-1] <= 1e-9 * spread[0]:
        raise UserError(f"{KEY} = {name}: the surface encloses zero volume (its vertices lie in one plane): "
                        "give the body a thickness")
    directed = np.r_[faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    if np.any(counts == 1):
        raise UserError(f"{KEY} = {name}: the surface is not closed ({np.sum(counts == 1)} edges border one "
                        "triangle): close it, it must bound a solid")
    if np.any(counts > 2):
        raise UserError(f"{KEY} = {name}: the surface is non-manifold ({np.sum(counts > 2)} edges border more "
                        "than two triangles): make each edge border exactly two, one solid without inner walls")
    if len(np.unique(directed, axis=0)) != len(directed):
        raise UserError(f"{KEY} = {name}: the surface's triangles are not consistently oriented "
                        "(an edge runs the same way in both its triangles): orient them all outward")
    pinched = pinched_vertices(faces, len(pts))
    if len(pinched):
        raise UserError(f"{KEY} = {name}: the surface is non-manifold at {len(pinched)} vertices where parts "
                        f"touch at a point (vertex {pts[pinched[0]].round(6).tolist()}): join them or pull them apart")
    _one_piece(name, pts, faces)
    volume = enclosed_volume(pts, faces)
    if abs(volume) <= 1e-9 * np.ptp(pts, axis=0).max() ** 3:
        raise UserError(f"{KEY} = {name}: the surface encloses zero volume: give the body a thickness")
    crossing = crossing_pairs(pts, faces)
    if len(crossing):
        where = pts[faces[crossing[0]]].mean(axis=(0, 1)).round(6).tolist()
        raise UserError(f"{KEY} = {name}: the surface intersects itself ({len(crossing)} pairs of triangles "
                        f"cross, the first near {where}): repair it (e.g. a boolean union in the CAD tool)")


def _one_piece(name: str, pts: np.ndarray, faces: np.ndarray) -> None:
    sizes = pieces(faces, len(pts))
    if len(sizes) > 1:
        raise UserError(f"{KEY} = {name}: the surface is {len(sizes)} separate bodies (of {', '.join(map(str, sizes))} "
                        "triangles; a cavity counts as one): a drone is one solid, join them or give one")


def _body2(name: str, points: np.ndarray, cells: dict) -> Body:
    if points.shape[1] == 3:
        if np.ptp(points[:, 2]) > 1e-9 * max(np.ptp(points[:, :2], axis=0).max(), 1e-300):
            raise UserError(f"{KEY} = {name}: a 2D drone's outline must lie in the X-Y plane (z varies)")
        points = points[:, :2]
    if "triangle" in cells:   # the boundary of a 2D mesh, re-meshed at drone.mesh.edge_length
        tris = cells["triangle"]
        a, b, c = (points[tris[:, k]] for k in range(3))
        cross = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
        tris = np.where((cross < 0)[:, None], tris[:, [0, 2, 1]], tris)
        return _outline(name, points, boundary_faces(tris))
    if "line" not in cells:
        raise UserError(f"{KEY} = {name}: holds no lines or triangles (cells: {', '.join(cells) or 'none'}); "
                        "a 2D drone needs a closed outline or a triangle mesh")
    return _outline(name, points, cells["line"])


def _merge(points: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident points (STL stores each triangle's corners apart), drop unused ones."""
    tol = 1e-9 * max(np.ptp(points, axis=0).max(), 1e-300)
    _, first, inverse = np.unique(np.round(points / tol), axis=0, return_index=True, return_inverse=True)
    cells = inverse.ravel()[cells]
    cells = cells[np.all(np.diff(np.sort(cells, axis=1), axis=1) > 0, axis=1)]   # collapsed ones
    width = cells.shape[1]
    used, cells = np.unique(cells, return_inverse=True)
    return points[first][used], cells.reshape(-1, width)


def _loops(segments: np.ndarray) -> list[list[int]]:
    """The closed loops the segments form; None where a vertex has other than two of them."""
    nbrs: dict[int, list[int]] = {}
    for a, b in segments:
        nbrs.setdefault(int(a), []).append(int(b))
        nbrs.setdefault(int(b), []).append(int(a))
    if any(len(v) != 2 for v in nbrs.values()):
        return None
    loops, seen = [], set()
    for start in nbrs:
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            nxt = nbrs[cur][0] if nbrs[cur][0] != prev else nbrs[cur][1]
            if nxt == start:
                break
            loop.append(nxt)
            seen.add(nxt)
            prev, cur = cur, nxt
        loops.append(loop)
    return loops


def _area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _inside(point: np.ndarray, ring: np.ndarray) -> bool:
    """Even-odd rule: ``point`` inside the closed polygon ``ring``."""
    a, b = ring, np.roll(ring, -1, axis=0)
    cross = (a[:, 1] > point[1]) != (b[:, 1] > point[1])
    x = a[:, 0] + (point[1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / np.where(cross, b[:, 1] - a[:, 1], 1.0)
    return bool(np.sum(cross & (x > point[0])) % 2)


def _outline(name: str, points: np.ndarray, segments: np.ndarray) -> Body:
    """Loops oriented as the 2D shapes are (outline counter-clockwise, holes clockwise: the
    body on the left of every segment), with a point in each hole for Triangle."""
    points, segments = _merge(points, np.asarray(segments, dtype=np.int64))
    loops = _loops(segments) if len(segments) >= 3 else None
    if loops is None:
        raise UserError(f"{KEY} = {name}: the outline is not closed (a vertex ends or branches it): "
                        "give closed polylines")
    rings = [points[loop] for loop in loops]
    rings_out, holes = [], []
    for k, ring in enumerate(rings):
        if abs(_area(ring)) <= 1e-9 * np.ptp(points, axis=0).max() ** 2:
            raise UserError(f"{KEY} = {name}: the outline encloses zero area")
        depth = sum(_inside(ring[0], other) for j, other in enumerate(rings) if j != k)
        hole = depth % 2 == 1
        ring = ring if (_area(ring) > 0) != hole else ring[::-1]
        if hole:   # just off a segment's midpoint, on the side away from the body
            d = ring[1] - ring[0]
            holes.append(0.5 * (ring[0] + ring[1]) + 1e-3 * np.array([d[1], -d[0]]))
        rings_out.append(ring)
    if len(rings_out) - len(holes) > 1:
        raise UserError(f"{KEY} = {name}: the outline is {len(rings_out) - len(holes)} separate bodies (closed "
                        "loops side by side, not one inside another): a drone is one body, join them or give one")
    vertices = np.vstack(rings_out)
    start = np.cumsum([0] + [len(r) for r in rings_out])
    segs = np.vstack([np.c_[np.arange(s, e), np.r_[np.arange(s + 1, e), s]] for s, e in zip(start[:-1], start[1:])])
    return Body(2, vertices, segs.astype(np.int32), np.array(holes).reshape(-1, 2), None)
