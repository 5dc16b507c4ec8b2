"""Write the example drone of one's own: an asymmetric three-armed plate as an STL in millimetres.

    python examples/make_tripod.py [out.stl]     # default: sdexp/conf/drone/tripod.stl

A hub of radius 0.5 m with three arms of different lengths and widths at 90, 200 and 325 deg
(from +X towards +Z), 0.2 m thick, lying in the X-Z plane with +Y up, as sdexp's drones do. It
is none of the paper's twelve shapes, and no symmetry makes its control easy. The file is what a
CAD tool would export: a closed, outward triangle surface, here in millimetres, so its config
(sdexp/conf/drone/tripod.yaml) says ``drone.mesh.scale: 0.001``. The rotors there are the points
ROTORS prints, on the upper surface: the hub's centre and 0.25 m in from each arm's tip.
"""
from __future__ import annotations

import sys
from pathlib import Path

import meshio
import numpy as np
import triangle

HUB = 0.5                                              # m
ARMS = [(90.0, 1.6, 0.45), (200.0, 1.25, 0.35), (325.0, 1.4, 0.4)]   # (deg, reach from centre, width) m
THICKNESS = 0.2                                        # m
INSET = 0.25                                           # m from an arm's tip to its rotor
SAMPLES = 240                                          # outline points


def inside(p: np.ndarray) -> np.ndarray:
    """The hub and the arms (capsules from the centre to their reach) as a point test, (k, 2)."""
    ok = np.hypot(p[:, 0], p[:, 1]) <= HUB
    for deg, reach, width in ARMS:
        axis = np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])
        r = width / 2
        t = np.clip(p @ axis, 0.0, reach - r)
        ok |= np.linalg.norm(p - t[:, None] * axis, axis=1) <= r
    return ok


def outline() -> np.ndarray:
    """The body is star-shaped about its centre: bisect each ray for where it leaves."""
    tips = np.radians([a for a, _, _ in ARMS])
    theta = np.linspace(0.0, 2 * np.pi, SAMPLES, endpoint=False)
    theta = theta[np.min(np.abs(theta[:, None] - tips), axis=1) > 1e-3]   # no point next to a tip ...
    theta = np.sort(np.r_[theta, tips])                                   # ... which is an outline point
    ray = np.c_[np.cos(theta), np.sin(theta)]
    lo, hi = np.zeros(len(theta)), np.full(len(theta), 2.0)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        ok = inside(mid[:, None] * ray)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return lo[:, None] * ray


def surface() -> tuple[np.ndarray, np.ndarray]:
    """Closed outward surface (metres): top and bottom caps from Triangle, walls along the outline."""
    ring = outline()
    n = len(ring)
    k = np.arange(n)
    tri = triangle.triangulate({"vertices": ring, "segments": np.c_[k, (k + 1) % n]}, "p")
    planar, caps = tri["vertices"], tri["triangles"]
    m = len(planar)
    # planar (x, z) counter-clockwise has normal -y: that is the bottom; the top is reversed
    bottom = np.c_[planar[:, 0], np.full(m, -THICKNESS / 2), planar[:, 1]]
    top = bottom * [1, -1, 1]
    k = np.arange(n)   # Triangle keeps the input vertices first: the outline is 0..n-1
    a, b = k, (k + 1) % n
    walls = np.r_[np.c_[a, b + m, b], np.c_[a, a + m, b + m]]
    faces = np.r_[caps, caps[:, [0, 2, 1]] + m, walls]
    return np.r_[bottom, top], faces


def rotors() -> list[list[float]]:
    """The hub's centre and a point INSET in from each arm tip, on the upper surface (m)."""
    out = [[0.0, THICKNESS / 2, 0.0]]
    for deg, reach, _ in ARMS:
        r = reach - INSET
        out.append([round(float(r * np.cos(np.radians(deg))), 4), THICKNESS / 2,
                    round(float(r * np.sin(np.radians(deg))), 4)])
    return out


def main(out: Path) -> None:
    points, faces = surface()
    meshio.write(out, meshio.Mesh(points * 1000.0, [("triangle", faces)]), file_format="stl", binary=True)
    print(f"wrote {out} ({len(faces)} triangles, millimetres); rotors (m): {rotors()}")


if __name__ == "__main__":
    default = Path(__file__).resolve().parents[1] / "sdexp" / "conf" / "drone" / "tripod.stl"
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else default)
