"""Sensor placement rule of supplement D, written down so every shape follows it.

1. Build a tree in the drone's plane: the root is the geometric centre, every rotor is a node,
   and each rotor hangs from the nearest node that is closer to the centre than itself
   (rotors within ``root_radius`` of the centre merge with the root).
2. Peripheral IMUs sit on the tree's edges, near the outer end: an edge that carries j IMUs
   holds them at fractions 0.8, 0.8 (j-1)/j, ... of the way from the parent to the child.
3. The sensors are spread over edges leaf edges first (they bend most), longest first, as
   evenly as the count allows; when there are fewer sensors than leaf edges, evenly spaced
   leaf edges (by angle around the centre from +X) get one each.
4. The order of s is the order of the IMUs by angle around the centre in [0, 2 pi) measured
   from +X, then by distance from it.
"""
from __future__ import annotations

import numpy as np

OUTER_FRACTION = 0.8


def _planar(points: np.ndarray) -> np.ndarray:
    """Coordinates in the drone's plane: (x, z) in 3D, (x, y) in 2D."""
    return points[:, [0, 2]] if points.shape[1] == 3 else points


def rotor_tree(center: np.ndarray, rotors: np.ndarray, root_radius: float) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """Edges (parent point, child point, child_is_leaf) of the sensor tree."""
    c = _planar(center[None])[0]
    r = _planar(rotors)
    dist = np.linalg.norm(r - c, axis=1)
    order = np.argsort(dist, kind="stable")
    nodes = [c]
    parents = {}
    for i in order:
        if dist[i] <= root_radius:
            continue  # merges with the root
        cand = np.array(nodes)
        closer = [k for k in range(len(nodes)) if np.linalg.norm(cand[k] - c) < dist[i] - 1e-9]
        k = min(closer, key=lambda k: np.linalg.norm(cand[k] - r[i]))
        parents[i] = cand[k]
        nodes.append(r[i])
    has_child = {tuple(np.round(p, 9)) for p in parents.values()}
    return [(p, r[i], tuple(np.round(r[i], 9)) not in has_child) for i, p in parents.items()]


def tree_imus(center: np.ndarray, rotors: np.ndarray, num_sensors: int, root_radius: float = 1e-6) -> np.ndarray:
    """Planar positions of ``num_sensors`` peripheral IMUs by the rule above, shape (n, 2)."""
    edges = rotor_tree(center, rotors, root_radius)
    if num_sensors == 0:
        return np.zeros((0, 2))
    if not edges:
        raise ValueError("no rotor lies away from the centre: the sensor tree has no edge")
    c = _planar(center[None])[0]
    angle = lambda q: np.mod(np.arctan2(q[1] - c[1], q[0] - c[0]), 2 * np.pi)  # noqa: E731
    leaves = [e for e in edges if e[2]]
    inner = [e for e in edges if not e[2]]
    counts = {}
    if num_sensors < len(leaves):
        by_angle = sorted(leaves, key=lambda e: angle(e[1]))
        picks = np.floor(np.arange(num_sensors) * len(by_angle) / num_sensors).astype(int)
        for k in picks:
            counts[id(by_angle[k])] = 1
        chosen = [by_angle[k] for k in picks]
    else:
        chosen = sorted(leaves, key=lambda e: -np.linalg.norm(e[1] - e[0])) + \
                 sorted(inner, key=lambda e: -np.linalg.norm(e[1] - e[0]))
        base, extra = divmod(num_sensors, len(chosen))
        for k, e in enumerate(chosen):
            counts[id(e)] = base + (1 if k < extra else 0)
    points = []
    for e in chosen:
        j = counts.get(id(e), 0)
        for i in range(j):
            f = OUTER_FRACTION * (j - i) / j
            points.append(e[0] + f * (e[1] - e[0]))
    pts = np.array(points)
    d = np.linalg.norm(pts - c, axis=1)
    theta = np.mod(np.arctan2(pts[:, 1] - c[1], pts[:, 0] - c[0]), 2 * np.pi)
    order = np.lexsort((d, np.round(theta, 9)))
    return pts[order]


def closest_gap(center: np.ndarray, planar: np.ndarray) -> float:
    """The least distance between planar IMU positions and the centre (the frame IMU's place)."""
    pts = np.r_[_planar(center[None]), planar]
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    return float(d[np.triu_indices(len(pts), 1)].min())


def most_imus(center: np.ndarray, rotors: np.ndarray, num_sensors: int, spacing: float,
              root_radius: float = 1e-6) -> int:
    """The most peripheral IMUs, up to ``num_sensors``, the rule places ``spacing`` or more apart
    (and from the centre): more crowd an edge, their patches binding the same faces."""
    for n in range(int(num_sensors), 0, -1):
        if closest_gap(center, tree_imus(center, rotors, n, root_radius)) >= spacing:
            return n
    return 0
