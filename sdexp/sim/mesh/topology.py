"""What makes a closed triangle surface one solid, beyond every edge bordering two triangles:
each vertex's triangles form one fan (no pinched vertex), the surface is one piece, and no two
triangles cross. sdexp.sim.mesh.meshfile checks a mesh file's surface with these before anything
is meshed: fTetWild meshes whatever it is given, a self-crossing or two-body surface included,
into something else without a word. Plain numpy and scipy; nothing of the simulator.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


def _labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def pieces(faces: np.ndarray, n: int) -> np.ndarray:
    """The triangle count of each connected piece of the surface on ``n`` vertices."""
    labels = _labels(n, np.r_[faces[:, 0], faces[:, 1]], np.r_[faces[:, 1], faces[:, 2]])
    return np.bincount(labels[faces[:, 0]])[np.unique(labels[faces[:, 0]])]


def pinched_vertices(faces: np.ndarray, n: int) -> np.ndarray:
    """Vertices whose triangles form more than one fan (two cones touching at their tips), on a
    closed, consistently oriented surface: each directed edge a -> b has its twin b -> a."""
    m = len(faces)
    directed = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)     # edge 3f + k starts at corner 3f + k
    ends = (np.arange(3 * m) // 3) * 3 + (np.arange(3 * m) % 3 + 1) % 3
    keys = directed[:, 0] * n + directed[:, 1]
    order = np.argsort(keys)
    twin = order[np.searchsorted(keys[order], directed[:, 1] * n + directed[:, 0])]
    corners = _labels(3 * m, np.arange(3 * m), ends[twin])   # corner of a in f ~ corner of a in the twin's face
    vertex = faces.ravel()
    fans = np.unique(np.c_[vertex, corners], axis=0)[:, 0]
    return np.flatnonzero(np.bincount(fans, minlength=n) > 1)


def _orient(a, b, c, d) -> np.ndarray:
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)


def _pierces(p, q, a, b, c, eps) -> np.ndarray:
    """Segment pq crosses the inside of triangle abc (strictly: touching does not count)."""
    d1, d2 = _orient(a, b, c, p), _orient(a, b, c, q)
    e = np.c_[_orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)]
    apart = (d1 * d2 < 0) & (np.abs(d1) > eps) & (np.abs(d2) > eps)
    return apart & (np.all(e > eps[:, None], axis=1) | np.all(e < -eps[:, None], axis=1))


def _candidates(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Pairs (i < j) of triangles whose bounding boxes share a cell of a grid as fine as the
    typical triangle (a plain all-pairs test is quadratic in the triangles)."""
    m = len(lo)
    h = max(float(np.median(np.max(hi - lo, axis=1))), 1e-12 * float(np.max(hi.max(0) - lo.min(0))))
    while True:   # coarser while the large triangles would fill too many cells
        first, last = np.floor((lo - lo.min(0)) / h).astype(np.int64), np.floor((hi - lo.min(0)) / h).astype(np.int64)
        span = last - first + 1
        count = np.prod(span, axis=1)
        if count.sum() <= 64 * m:
            break
        h *= 2
    tri = np.repeat(np.arange(m), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sx, sy = span[tri, 0], span[tri, 1]
    cell = first[tri] + np.c_[k % sx, (k // sx) % sy, k // (sx * sy)]
    side = cell.max() + 1
    key = lambda c: (c[:, 0] * side + c[:, 1]) * side + c[:, 2]   # noqa: E731
    cells = key(cell)
    order = np.argsort(cells, kind="stable")
    cells, tri = cells[order], tri[order]
    end = np.searchsorted(cells, cells, side="right")             # each entry pairs with the rest of its cell
    after = end - np.arange(len(cells)) - 1
    start = np.repeat(np.arange(len(cells)), after)
    step = np.arange(after.sum()) - np.repeat(np.cumsum(after) - after, after) + 1
    i, j = tri[start], tri[start + step]
    once = cells[start] == key(np.maximum(first[i], first[j]))   # a pair sharing cells: in its lowest shared one
    return np.c_[i[once], j[once]]


def crossing_pairs(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Pairs of triangles that cross each other (an edge of one through the inside of the
    other), neighbours across an edge left out; touching and coplanar overlap are not counted."""
    tri = points[faces]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    pairs = _candidates(lo, hi)
    i, j = pairs.T
    shared = (faces[i][:, :, None] == faces[j][:, None, :]).sum(axis=(1, 2))
    keep = (shared < 2) & np.all(lo[i] <= hi[j], axis=1) & np.all(lo[j] <= hi[i], axis=1)
    i, j = i[keep], j[keep]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    for first in (True, False):   # the cheap test first: crossing needs corners strictly on both sides
        s, t = (i, j) if first else (j, i)
        side = np.einsum("ikj,ij->ik", tri[s] - tri[t, :1], normal[t])
        tol = 1e-10 * np.max(hi[t] - lo[t], axis=1)[:, None] ** 3
        keep = np.any(side > tol, axis=1) & np.any(side < -tol, axis=1)
        i, j = i[keep], j[keep]
    size = np.maximum(np.max(hi[i] - lo[i], axis=1), np.max(hi[j] - lo[j], axis=1))
    eps = 1e-10 * size ** 3
    hit = np.zeros(len(i), dtype=bool)
    for s, t in ((i, j), (j, i)):
        for k in range(3):
            p, q = tri[s, k], tri[s, (k + 1) % 3]
            hit |= _pierces(p, q, tri[t, 0], tri[t, 1], tri[t, 2], eps)
    return np.c_[i[hit], j[hit]]
