"""Structured box meshes for the physics validation (beams, blocks): a grid of hexahedra cut
into six tets each (Kuhn triangulation), or of quads cut into two triangles in 2D."""
from __future__ import annotations

import itertools

import numpy as np

from sdexp.sim.physics.fem import signed_volumes

# Kuhn triangulation of the unit cube: one tet per permutation of the axes.
_KUHN = [
    [0, (1 << p[0]), (1 << p[0]) | (1 << p[1]), 7] for p in itertools.permutations(range(3))
]


def box_tets(counts: tuple[int, int, int], lengths: tuple[float, float, float],
             origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    nx, ny, nz = counts
    axes = [np.linspace(o, o + L, n + 1) for o, L, n in zip(origin, lengths, counts)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    points = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
    vid = np.arange(len(points)).reshape(nx + 1, ny + 1, nz + 1)
    corner = lambda c, i, j, k: vid[i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)]  # noqa: E731
    tets = []
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        for t in _KUHN:
            tets.append([corner(c, i, j, k) for c in t])
    tets = np.array(tets, dtype=np.int32)
    flip = signed_volumes(points, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return points, tets


def box_tris(counts: tuple[int, int], lengths: tuple[float, float],
             origin: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    nx, ny = counts
    axes = [np.linspace(o, o + L, n + 1) for o, L, n in zip(origin, lengths, counts)]
    X, Y = np.meshgrid(*axes, indexing="ij")
    points = np.c_[X.ravel(), Y.ravel()]
    vid = np.arange(len(points)).reshape(nx + 1, ny + 1)
    tris = []
    for i, j in itertools.product(range(nx), range(ny)):
        a, b, c, d = vid[i, j], vid[i + 1, j], vid[i + 1, j + 1], vid[i, j + 1]
        # alternate the diagonal so the mesh has no preferred direction
        tris += [[a, b, c], [a, c, d]] if (i + j) % 2 == 0 else [[a, b, d], [b, c, d]]
    return points, np.array(tris, dtype=np.int32)
