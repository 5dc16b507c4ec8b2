"""The six 3D drones of the paper's table (supplement B) as closed triangle surfaces.

Every drone is a plate. Its planar body lies in the X-Z plane; it is triangulated with
Triangle, lifted onto a mid-surface y = g(rho) that is radial about the centre (g = 0 for the
flat drones, a dome for the octopus's head, a bowl for the orange peel) and thickened by t/2
to each side along the mid-surface normal, so the wall is t thick on slopes too.

The bodies are unions of pieces that are star-shaped about the centre (discs; lobes that are
the convex hull of a circle at the centre and one at the tip; the leaf's pointed ellipse), so
every ray from the centre leaves the body once and the outline is a polar curve r(theta).

Sizes: a generator scales its planar body (x and z apart) and, for the curved drones, the rise
of the mid-surface until the surface's bounding box is ``size``; the box is then centred on
x and z, and y = 0 is the mid-plane of the flat part of the plate. Rotors sit at polar
positions about the centre, peripheral IMUs where the placement rule of supplement D puts
them, all lifted onto the upper surface (the same x, z; y and the normal of the upper surface
there).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import triangle

from sdexp.sim.mesh.placement import tree_imus
from sdexp.sim.mesh.shape import Shape

Inside = Callable[[np.ndarray], np.ndarray]   # (k, 2) planar points -> (k,) bool
Profile = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # rho -> (g, dg/drho)

_SEGMENT = 0.1      # outline segment of the input surface (m); fTetWild coarsens it
_CURVED_EDGE = 0.15  # in-plane triangle edge on a curved drone, so the surface follows g


# ---------------------------------------------------------------------------------------
# planar bodies

def _disc(radius: float) -> Inside:
    return lambda p: np.hypot(p[:, 0], p[:, 1]) <= radius


def _lobe(angle: float, root_half: float, tip_half: float, length: float) -> Inside:
    """Convex hull of a circle of radius ``root_half`` at the centre and one of ``tip_half``
    touching radius ``length`` along ``angle`` (rad from +X towards +Z); exact signed distance
    of the uneven capsule (I. Quilez)."""
    h = length - tip_half
    b = (root_half - tip_half) / h
    a = np.sqrt(1.0 - b * b)
    axis = np.array([np.cos(angle), np.sin(angle)])
    normal = np.array([-axis[1], axis[0]])

    def inside(p: np.ndarray) -> np.ndarray:
        u, v = p @ axis, np.abs(p @ normal)
        k = a * u - b * v
        dist = np.where(k < 0, np.hypot(u, v) - root_half,
                        np.where(k > a * h, np.hypot(u - h, v) - tip_half,
                                 a * v + b * u - root_half))
        return dist <= 0
    return inside


def _union(*parts: Inside) -> Inside:
    return lambda p: np.logical_or.reduce([part(p) for part in parts])


def _polar_outline(inside: Inside, r_max: float, key_angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed outline (k, 2), counter-clockwise in (x, z), of a body star-shaped about 0, and
    the same outline as traced (rays about a millimetre apart: corners kept to that).

    Each sector between consecutive ``key_angles`` (lobe axes, symmetry axes) is resampled
    on its own with its ends kept, so lobe tips are outline points and a symmetric body gets
    a symmetric outline, whose bounding box is then exact and centred."""
    keys = np.sort(np.mod(key_angles, 2 * np.pi))
    points, traced = [], []
    for a, b in zip(keys, np.r_[keys[1:], keys[0] + 2 * np.pi]):
        theta = np.linspace(a, b, int(np.ceil(2048 * (b - a) / np.pi)) + 1)
        ray = np.c_[np.cos(theta), np.sin(theta)]
        lo, hi = np.zeros(len(theta)), np.full(len(theta), r_max)
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            ok = inside(mid[:, None] * ray)
            lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
        points.append(_resample(lo[:, None] * ray)[:-1])
        traced.append((lo[:, None] * ray)[:-1])
    return np.vstack(points), np.vstack(traced)


def _circle(radius: float, segment: float = _SEGMENT) -> np.ndarray:
    n = 4 * max(4, int(np.ceil(np.pi * radius / (2 * segment))))  # points on both axes
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return radius * np.c_[np.cos(t), np.sin(t)]


def _closed_loops(loops: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Vertices and segments (a list of (k, 2) index arrays) of closed polylines."""
    segments, start = [], 0
    for loop in loops:
        k = np.arange(len(loop))
        segments.append(np.c_[start + k, start + (k + 1) % len(loop)])
        start += len(loop)
    return np.vstack(loops), segments


def _split_at_zero(loop: np.ndarray, cols: list[int]) -> np.ndarray:
    """The closed polyline ``loop`` with a vertex wherever it crosses coordinate c = 0 for c in
    ``cols``, exactly 0 there (points within 1e-12 of a plane are put on it)."""
    loop = np.where(np.abs(loop) < 1e-12, 0.0, loop)
    for c in cols:
        out = []
        for p, q in zip(loop, np.roll(loop, -1, axis=0)):
            out.append(p)
            if p[c] * q[c] < 0:
                x = p + (q - p) * (p[c] / (p[c] - q[c]))
                x[c] = 0.0
                out.append(x)
        loop = np.array(out)
    return loop


def _resample_closed(loop: np.ndarray, spacing: float) -> np.ndarray:
    """The closed polyline ``loop`` as points about ``spacing`` apart along it (at least
    eight), equal arc length, the first point kept."""
    closed = np.vstack([loop, loop[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    t = np.linspace(0.0, s[-1], max(8, int(round(s[-1] / spacing))), endpoint=False)
    return np.c_[np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])]


def _turns(loop: np.ndarray) -> np.ndarray:
    """The signed angle a closed polyline turns by at each vertex (counter-clockwise > 0)."""
    d = np.diff(np.vstack([loop, loop[:1]]), axis=0)
    d_in = np.roll(d, 1, axis=0)
    return np.arctan2(d_in[:, 0] * d[:, 1] - d_in[:, 1] * d[:, 0], np.einsum("ij,ij->i", d_in, d))


def _corners(loop: np.ndarray, min_turn_deg: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the corners of a traced closed polyline (where it turns by more than
    ``min_turn_deg``; a corner between two rays shows as two or three turning vertices, the
    sharpest kept) and whether each is re-entrant (turning against the loop's orientation)."""
    turn = _turns(loop)
    sharp = np.abs(turn) > np.radians(min_turn_deg)
    keep = sharp & (np.abs(turn) >= np.roll(np.abs(turn), 1)) & (np.abs(turn) >= np.roll(np.abs(turn), -1))
    idx = np.flatnonzero(keep)
    area = 0.5 * np.sum(loop[:, 0] * np.roll(loop[:, 1], -1) - np.roll(loop[:, 0], -1) * loop[:, 1])
    return idx, np.sign(turn[idx]) != np.sign(area)


def _graded_closed(loop: np.ndarray, spacing: float, finest: float = 0.25, growth: float = 0.3,
                   sagitta: float = 1e-3) -> np.ndarray:
    """The traced closed polyline ``loop`` as points about ``spacing`` apart with its corners
    kept as points, the spacing graded toward its re-entrant corners (``finest`` x spacing
    there, growing by ``growth`` of the distance along the outline: where the stress of a
    re-entrant corner concentrates, which a uniform mesh resolves last) and short enough on
    curved stretches that a chord stays within ``sagitta`` of the arc (design units): every
    refinement then meshes the same body. (Chords 0.23 m long cut 1.6 cm off the flower's petal
    tips: its volume grew 3.4% from edge 0.35 to 0.12 m, and its compliance fell with it.)"""
    closed = np.vstack([loop, loop[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    corners, reentrant = _corners(loop)
    turn = np.abs(_turns(loop))
    turn[corners] = 0.0                            # a corner is a point of the outline, not a bend
    ds = 0.5 * (seg + np.roll(seg, 1))             # the outline's length per vertex
    window = np.ones(9) / 9                        # curvature over a few rays (the trace is noisy)
    kappa = np.convolve(np.r_[turn[-4:], turn, turn[:4]], window, "valid") / np.maximum(
        np.convolve(np.r_[ds[-4:], ds, ds[:4]], window, "valid"), 1e-12)
    h = np.minimum(spacing, np.sqrt(8 * sagitta / np.maximum(kappa, 1e-12)))
    h = np.r_[h, h[:1]]
    for c in corners[reentrant]:   # distance along the closed outline, both ways round
        dist = np.abs(s - s[c])
        h = np.minimum(h, finest * spacing + growth * np.minimum(dist, s[-1] - dist))
    # cumulative count of segments: points where it crosses integers (per piece between corners)
    count = np.concatenate([[0.0], np.cumsum(np.diff(s) * 0.5 * (1 / h[1:] + 1 / h[:-1]))])
    ends = np.r_[corners, corners[:1] + len(loop)] if len(corners) else np.array([0, len(loop)])
    ends_s = np.r_[s[:-1], s[-1] + s]   # arc length and count over two turns of the loop
    count2 = np.r_[count[:-1], count[-1] + count]
    out = []
    for a, b in zip(ends[:-1], ends[1:]):
        n = max(1, int(round(count2[b] - count2[a])))
        t = np.interp(np.linspace(count2[a], count2[b], n + 1)[:-1], count2[a:b + 1], ends_s[a:b + 1])
        t = np.mod(t, s[-1])
        out.append(np.c_[np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])
    return np.vstack(out)


def _resample(line: np.ndarray) -> np.ndarray:
    """Points about _SEGMENT apart along an open polyline, equal arc length, ends kept."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    t = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / _SEGMENT))) + 1)
    return np.c_[np.interp(t, s, line[:, 0]), np.interp(t, s, line[:, 1])]


# ---------------------------------------------------------------------------------------
# mid-surfaces

def _flat(rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros_like(rho), np.zeros_like(rho)


def _dome(radius: float) -> Callable[[float], Profile]:
    """Raised cosine of unit rise over ``radius`` (C1 where it meets the flat plate)."""
    def profile(rise: float) -> Profile:
        def g(rho):
            s = np.clip(rho / radius, 0.0, 1.0)
            return (rise * 0.5 * (1 + np.cos(np.pi * s)),
                    -rise * 0.5 * np.pi / radius * np.sin(np.pi * s))
        return g
    return profile


def _bowl(flat_radius: float, span: float) -> Callable[[float], Profile]:
    """Flat up to ``flat_radius``, then rising as ((rho - flat_radius) / span)^2."""
    def profile(rise: float) -> Profile:
        def g(rho):
            s = np.maximum(rho - flat_radius, 0.0) / span
            return rise * s * s, 2 * rise * s / span
        return g
    return profile


# ---------------------------------------------------------------------------------------
# plates

@dataclass
class _Design:
    """A drone in design coordinates: planar body centred at the origin, before fitting."""
    name: str
    inside: Inside
    loops: list[np.ndarray]     # outline first, then hole outlines
    hole_points: list[tuple[float, float]]
    thickness: float
    profile: Callable[[float], Profile] | None = None   # rise -> g; None: flat
    rise: float = 0.0           # first guess of the mid-surface rise (curved drones)
    taper: Callable[[np.ndarray], np.ndarray] | None = None  # design points -> thickness fraction; None: 1
    traced: list[np.ndarray] | None = None   # the loops as traced, corners kept (outline "exact"); None: loops


class _Plate:
    """A fitted drone: the planar map p_design -> scale * p_design + shift and the rise."""

    def __init__(self, design: _Design, size: tuple[float, float, float]):
        self.d = design
        points, segments = _closed_loops(design.loops)
        if design.profile:  # a vertex at the centre, where the dome peaks and a rotor sits
            points = np.vstack([points, [[0.0, 0.0]]])
        self.planar, self.tris = self._triangulate(points, np.vstack(segments))
        self.scale, self.shift = np.ones(2), np.zeros(2)
        self.g = design.profile(design.rise) if design.profile else _flat
        self._fit(np.asarray(size, dtype=float))

    def _triangulate(self, points: np.ndarray, segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pslg = {"vertices": points, "segments": segments}
        if self.d.hole_points:
            pslg["holes"] = np.array(self.d.hole_points, dtype=float)
        # Flat, even caps need no inner vertex (fTetWild would spend seconds simplifying them
        # away); curved or tapered ones do, to follow the surface.
        opts = f"pq30a{_CURVED_EDGE ** 2 * np.sqrt(3) / 4:.6f}" if self.d.profile or self.d.taper else "p"
        tri = triangle.triangulate(pslg, opts)
        return tri["vertices"], tri["triangles"].astype(np.int64)

    def _fit(self, size: np.ndarray) -> None:
        """Scale x and z, shift, and (curved drones) raise until the bounding box is size."""
        rise = self.d.rise
        axes = [0, 1, 2] if self.d.profile else [0, 2]
        for _ in range(30):
            v = self._surface_vertices()
            lo, hi = v.min(axis=0), v.max(axis=0)
            ext = hi - lo
            centred = np.all(np.abs(lo + hi)[[0, 2]] < 1e-9)
            if centred and np.all(np.abs(ext / size - 1)[axes] < 1e-6):
                break
            self.scale *= size[[0, 2]] / ext[[0, 2]]
            self.shift -= 0.5 * (lo + hi)[[0, 2]]
            if self.d.profile:
                rise += size[1] - ext[1]
                self.g = self.d.profile(rise)
        else:
            raise ValueError(f"{self.d.name}: cannot fit its surface to size {size.tolist()} "
                             f"(reached {ext.round(4).tolist()})")
        self._check_curvature()

    def _check_curvature(self) -> None:
        rho = np.linspace(1e-3, np.linalg.norm(self.planar * self.scale, axis=1).max(), 2000)
        g, dg = self.g(rho)
        ddg = np.gradient(dg, rho)
        w = np.sqrt(1 + dg * dg)
        kappa = np.maximum(np.abs(ddg) / w ** 3, np.abs(dg) / (rho * w))
        if 0.5 * self.d.thickness * kappa.max() >= 0.9:
            raise ValueError(f"{self.d.name}: thickness {self.d.thickness} is too large for the "
                             f"bend of its mid-surface (radius {1 / kappa.max():.3f} m)")

    def _mid(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mid-surface points and unit upward normals over planar points q (k, 2)."""
        d = q - self.shift
        rho = np.hypot(d[:, 0], d[:, 1])
        g, dg = self.g(rho)
        grad = dg[:, None] * d / np.maximum(rho, 1e-12)[:, None]
        n = np.c_[-grad[:, 0], np.ones(len(q)), -grad[:, 1]]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return np.c_[q[:, 0], g, q[:, 1]], n

    def _half_thickness(self, q: np.ndarray) -> np.ndarray:
        """Half the wall thickness (k, 1) over fitted planar points q (k, 2)."""
        t = np.full(len(q), 0.5 * self.d.thickness)
        if self.d.taper:
            t *= self.d.taper((q - self.shift) / self.scale)
        return t[:, None]

    def _surface_vertices(self, planar: np.ndarray | None = None) -> np.ndarray:
        q = (self.planar if planar is None else planar) * self.scale + self.shift
        mid, n = self._mid(q)
        t = self._half_thickness(q)
        return np.vstack([mid + t * n, mid - t * n])

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Closed surface: top cap (normal +y), bottom cap, walls along the boundary."""
        return self._closed(self.planar, self.tris)

    def _closed(self, planar: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The closed surface over the planar triangles ``tri`` (vertices ``planar``)."""
        used, tri = np.unique(tri, return_inverse=True)
        planar, tri = planar[used], tri.reshape(-1, 3)
        n = len(planar)
        # Triangle returns triangles counter-clockwise in (x, z), whose normal is -y.
        bottom = tri + n
        top = tri[:, [0, 2, 1]]
        edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        key = np.sort(edges, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        a, b = edges[counts[inverse.ravel()] == 1].T   # boundary, as the bottom cap runs it
        walls = np.concatenate([np.c_[b + n, a + n, a], np.c_[b + n, a, b]])
        return self._surface_vertices(planar), np.concatenate([top, bottom, walls]).astype(np.int32)

    def cell_surface(self, axes: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Closed surface of the part of the plate on the positive side of the mirror planes
        through the centre normal to ``axes`` (0: x, 2: z): the cell that, meshed and reflected
        across them (``sdexp.sim.mesh.mirror``), gives a mesh exactly as symmetric as the design."""
        cols = [{0: 0, 2: 1}[a] for a in axes]   # planar (x, z) columns of the cut axes
        opts = f"pq30a{_CURVED_EDGE ** 2 * np.sqrt(3) / 4:.6f}" if self.d.profile or self.d.taper else "p"
        return self._closed(*self._planar_cell(cols, opts))

    def _planar_cell(self, cols: list[int], options: str, spacing: float | None = None,
                     exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Planar triangles of the part on the positive side of the planes c = 0 for c in
        ``cols`` (the whole outline when empty): the outline (resampled ``spacing`` apart, in
        design coordinates, if given; ``exact``: the traced outline, its corners kept and the
        spacing graded toward the re-entrant ones) split where it crosses a plane, the planes'
        chords through the body constrained, so no triangle straddles a plane."""
        if not np.all(np.abs(self.shift[cols]) < 1e-9):
            raise ValueError(f"{self.d.name}: the body is not centred across the mirror plane(s)")
        if spacing is None:
            loops = self.d.loops
        elif exact:
            loops = [_graded_closed(loop, spacing) for loop in (self.d.traced or self.d.loops)]
        else:
            loops = [_resample_closed(loop, spacing) for loop in self.d.loops]
        points, segments = _closed_loops([_split_at_zero(loop, cols) for loop in loops])
        if self.d.profile or len(cols) == 2:   # the dome's peak, or where the two planes cross
            points = np.vstack([points, np.zeros((1, 2))])
        for c in cols:   # chords of the plane through the body, between consecutive crossings
            on = np.flatnonzero(points[:, c] == 0.0)
            on = on[np.argsort(points[on, 1 - c])]
            mid = 0.5 * (points[on[:-1]] + points[on[1:]])
            inside = self.d.inside(mid) & (np.diff(points[on, 1 - c]) > 0)
            segments.append(np.c_[on[:-1], on[1:]][inside])
        pslg = {"vertices": points, "segments": np.vstack(segments)}
        if self.d.hole_points:
            pslg["holes"] = np.array(self.d.hole_points, dtype=float)
        tri = triangle.triangulate(pslg, options)
        planar, tris = tri["vertices"], tri["triangles"].astype(np.int64)
        centroid = planar[tris].mean(axis=1)
        return planar, tris[np.all(centroid[:, cols] > 0, axis=1)] if cols else tris

    def layered_mesh(self, edge: float, layers: int, axes: tuple[int, ...] = (),
                     exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """A tet mesh that follows the plate: its outline triangulated (Triangle, quality 30
        deg, triangles of about ``edge`` on the fitted body) and extruded along the mid-surface
        normals through the thickness in ``layers`` layers, each prism cut into three tets
        (the diagonal of a side face from its lower-indexed bottom node, so neighbours agree).
        No slivers, so a larger stable step than fTetWild's mesh; deterministic. With ``axes``
        only the cell on the positive side of the mirror planes (sdexp.sim.mesh.mirror reflects it).
        ``exact`` (drone.mesh.outline): the design's outline with its corners, graded toward the
        re-entrant ones (_graded_closed), not resampled evenly (which cuts a notch narrower
        than ``edge``: the flower's notch bottoms at 0.63-0.69 m from the centre, not 0.60)."""
        cols = [{0: 0, 2: 1}[a] for a in axes]
        area = edge ** 2 * np.sqrt(3) / 4 / self.scale.prod()   # in design coordinates
        planar, tris = self._planar_cell(cols, f"pq30a{area:.8f}", edge / np.sqrt(self.scale.prod()), exact)
        used, tris = np.unique(tris, return_inverse=True)
        planar, tris = planar[used], tris.reshape(-1, 3)
        q = planar * self.scale + self.shift
        mid, normal = self._mid(q)
        half = self._half_thickness(q)
        n = len(q)
        points = np.vstack([mid + (2 * k / layers - 1) * half * normal for k in range(layers + 1)])
        v = np.sort(tris, axis=1)
        tets = []
        for k in range(layers):
            b, t = v + k * n, v + (k + 1) * n
            tets += [np.c_[b[:, 0], b[:, 1], b[:, 2], t[:, 2]], np.c_[b[:, 0], b[:, 1], t[:, 1], t[:, 2]],
                     np.c_[b[:, 0], t[:, 0], t[:, 1], t[:, 2]]]
        tets = np.vstack(tets)
        d = points[tets[:, 1:]] - points[tets[:, :1]]
        flip = np.linalg.det(d) < 0
        tets[flip] = tets[flip][:, [0, 2, 1, 3]]
        return points, tets.astype(np.int32)

    def lift(self, xz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points of the upper surface at planar positions xz (k, 2), its normals there, and
        whether each lies over the body."""
        xz = np.atleast_2d(np.asarray(xz, dtype=float))
        q = xz.copy()
        for _ in range(60):   # the upper surface is mid + t n: find the mid point q under xz
            _, n = self._mid(q)
            q = xz - self._half_thickness(q) * n[:, [0, 2]]
        mid, n = self._mid(q)
        points = mid + self._half_thickness(q) * n
        points[:, [0, 2]] = xz   # exact, not to the fixed point's tolerance
        return points, n, self.d.inside((q - self.shift) / self.scale)

    def center(self) -> np.ndarray:
        """The mid-surface point over the planar centre (the root of the sensor tree)."""
        mid, _ = self._mid(self.shift[None])
        return mid[0]


def _anchors(plate: _Plate, what: str, xz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points, normals, on_body = plate.lift(xz)
    if not on_body.all():
        raise ValueError(f"{plate.d.name}: {what} anchor(s) {np.flatnonzero(~on_body).tolist()} "
                         f"fall off the body; check the shape's params")
    return points, normals


def _finish(plate: _Plate, radii: np.ndarray, angles: np.ndarray, num_sensors: int,
            ring_frame: bool = False) -> Shape:
    """Rotors at polar positions about the centre; peripheral IMUs by the placement rule.

    The rotor radii are scaled isotropically: the rule hangs a rotor from the nearest rotor
    closer to the centre, so rotors meant to be equally far must stay exactly so."""
    vertices, faces = plate.surface()
    radii = np.asarray(radii, dtype=float) * np.sqrt(plate.scale.prod())
    xz = plate.shift + radii[:, None] * _at(angles, 1.0)
    rotors, rotor_normals = _anchors(plate, "rotor", xz)
    center = plate.center()
    imus, imu_normals = _anchors(plate, "IMU", tree_imus(center, rotors, num_sensors)) \
        if num_sensors else (np.zeros((0, 3)), np.zeros((0, 3)))
    if ring_frame:
        frame, frame_normals = imus, imu_normals
    else:
        frame, frame_normals = _anchors(plate, "centre IMU", plate.shift[None])
    return Shape(dim=3, vertices=vertices, faces=faces, holes=np.zeros((0, 3)), center=center,
                 rotors=rotors, rotor_normals=rotor_normals, imus=imus, imu_normals=imu_normals,
                 frame_imus=frame, frame_normals=frame_normals, cell_surface=plate.cell_surface,
                 layered_mesh=plate.layered_mesh)


# ---------------------------------------------------------------------------------------
# checks shared by the generators

def _params(name: str, params: dict, defaults: dict) -> dict:
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(f"{name}: unknown params {unknown}; known: {sorted(defaults)}")
    merged = {**defaults, **{k: float(v) for k, v in params.items()}}
    bad = sorted(k for k, v in merged.items() if not v > 0)
    if bad:
        raise ValueError(f"{name}: params {bad} must be > 0")
    return merged


def _count(name: str, what: str, have: int, got: int, key: str) -> None:
    if have != got:
        raise ValueError(f"{name} has {what}, drone.{key} = {got}")


def _thickness(name: str, size, thickness: float | None,
               curved_default: float | None = None) -> float:
    """Plate thickness: the y size for a flat drone unless given; for a curved drone the
    given one or its default, below the y size (which is the height of the bent plate)."""
    if curved_default is None:
        t = float(size[1]) if thickness is None else float(thickness)
        ok = t > 0
    else:
        t = curved_default if thickness is None else float(thickness)
        ok = 0 < t < float(size[1])
    if not ok:
        raise ValueError(f"{name}: plate thickness {t} must be > 0"
                         + ("" if curved_default is None else f" and < size[1] = {size[1]}"))
    return t


def _lobes(name: str, disc_radius: float, angles: np.ndarray, root_width: float,
           tip_width: float, length: float) -> Inside:
    """A central disc and one lobe per angle reaching ``length``."""
    if not (abs(root_width - tip_width) / 2 < length - tip_width / 2 and disc_radius < length):
        raise ValueError(f"{name}: a disc of radius {disc_radius} and lobes {root_width} wide at "
                         f"the root and {tip_width} at the tip do not fit in radius {length}")
    return _union(_disc(disc_radius),
                  *[_lobe(a, root_width / 2, tip_width / 2, length) for a in angles])


def _angles(count: int, first: float = 0.0) -> np.ndarray:
    return first + 2 * np.pi * np.arange(count) / count


def _at(angles: np.ndarray, radius: float) -> np.ndarray:
    return radius * np.c_[np.cos(angles), np.sin(angles)]


# ---------------------------------------------------------------------------------------
# the six drones (default proportions in metres, for the paper's sizes)

def _lobe_taper(start: float, ramp: float, lobe: float) -> Callable[[np.ndarray], np.ndarray]:
    """Thickness fraction: 1 within radius ``start``, ``lobe`` beyond ``start + ramp``, a smooth
    step between (no sharp re-entrant corner for the mesher)."""
    def taper(p: np.ndarray) -> np.ndarray:
        x = np.clip((np.hypot(p[:, 0], p[:, 1]) - start) / ramp, 0.0, 1.0)
        return 1.0 - (1.0 - lobe) * x * x * (3.0 - 2.0 * x)
    return taper


def _hub_with_lobes(name, size, thickness, num_rotors, num_sensors, p, keys, lobes) -> Shape:
    """A flat hub with ``lobes`` tapered lobes along equal angles (the first along +X); a rotor
    at the centre and near each lobe tip. ``keys``: the names of (hub radius, lobe root width,
    lobe tip width) in ``p``; ``p["lobe_thickness"]``: the lobes' thickness as a fraction of the
    hub's (1: an even plate; a starfish is thick in the middle, thin in its arms), thinning from
    ``p["thin_from"]`` x the hub radius over a quarter of the lobes' length (below 1: only a
    central pod keeps the full thickness)."""
    _count(name, f"{lobes + 1} rotors (centre + {lobes} lobes)", lobes + 1, num_rotors, "num_rotors")
    length, angles = 0.5 * float(size[0]), _angles(lobes)
    hub, root, tip = (p[k] for k in keys)
    if not (p["lobe_thickness"] <= 1 and p["thin_from"] <= 1):
        raise ValueError(f"{name}: params.lobe_thickness = {p['lobe_thickness']} and params.thin_from = "
                         f"{p['thin_from']} must be in (0, 1] (fractions of the hub's thickness and radius)")
    body = _lobes(name, hub, angles, root, tip, length)
    outline, traced = _polar_outline(body, 2 * length, angles)
    design = _Design(name, body, [outline], [], _thickness(name, size, thickness),
                     taper=_lobe_taper(p["thin_from"] * hub, 0.25 * (length - hub), p["lobe_thickness"])
                     if p["lobe_thickness"] != 1 else None, traced=[traced])
    radii = np.r_[0.0, np.full(len(angles), length - p["rotor_inset"])]
    return _finish(_Plate(design, size), radii, np.r_[0.0, angles], num_sensors)


def make_flower(size, thickness, num_rotors, num_sensors, params) -> Shape:
    """Central disc and 8 petals; a rotor at the centre and near each petal tip."""
    p = _params("flower", params, {"disc_radius": 0.6, "petal_root_width": 0.2, "petal_width": 0.8,
                                   "rotor_inset": 0.3, "lobe_thickness": 1.0, "thin_from": 1.0})
    return _hub_with_lobes("flower", size, thickness, num_rotors, num_sensors, p,
                           ("disc_radius", "petal_root_width", "petal_width"), 8)


def make_star(size, thickness, num_rotors, num_sensors, params) -> Shape:
    """Starfish: central body and 4 tapered wings along +-X and +-Z; a rotor at the centre
    and near each wing tip."""
    p = _params("star", params, {"body_radius": 0.8, "wing_root_width": 1.4, "wing_tip_width": 0.5,
                                 "rotor_inset": 0.3, "lobe_thickness": 1.0, "thin_from": 1.0})
    return _hub_with_lobes("star", size, thickness, num_rotors, num_sensors, p,
                           ("body_radius", "wing_root_width", "wing_tip_width"), 4)


def make_octopus(size, thickness, num_rotors, num_sensors, params) -> Shape:
    """Head whose shell domes up to the full height, and 8 arms in the plane; a rotor on top
    of the head and near each arm tip. ``thickness`` is the shell's (default 0.15 m)."""
    name = "octopus"
    p = _params(name, params, {"head_radius": 0.9, "arm_root_width": 0.6, "arm_tip_width": 0.2,
                               "rotor_inset": 0.25})
    _count(name, "9 rotors (head + 8 arms)", 9, num_rotors, "num_rotors")
    length, angles = 0.5 * float(size[0]), _angles(8)
    body = _lobes(name, p["head_radius"], angles, p["arm_root_width"], p["arm_tip_width"], length)
    t = _thickness(name, size, thickness, curved_default=0.15)
    outline, traced = _polar_outline(body, 2 * length, angles)
    design = _Design(name, body, [outline], [], t, _dome(p["head_radius"]), float(size[1]) - t,
                     traced=[traced])
    radii = np.r_[0.0, np.full(len(angles), length - p["rotor_inset"])]
    return _finish(_Plate(design, size), radii, np.r_[0.0, angles], num_sensors)


def make_orange_peel(size, thickness, num_rotors, num_sensors, params) -> Shape:
    """A peeled orange opened into 5 petals that rise from a flat base like a bowl, one petal
    along +Z; a rotor on each petal. ``thickness`` is the peel's (default 0.1 m)."""
    name = "orange_peel"
    p = _params(name, params, {"base_radius": 0.45, "petal_root_width": 0.3, "petal_width": 0.9,
                               "rotor_inset": 0.85})
    _count(name, "5 rotors (one per petal)", 5, num_rotors, "num_rotors")
    # Five petals with round tips of radius w/2, one along +Z, reaching R from the centre,
    # span R (1 + cos 36 deg) + (w/2)(1 - cos 36 deg) along z (the bend takes the rest).
    w, cos36 = p["petal_width"], np.cos(np.pi / 5)
    length, angles = (float(size[2]) - 0.5 * w * (1 - cos36)) / (1 + cos36), _angles(5, np.pi / 2)
    body = _lobes(name, p["base_radius"], angles, p["petal_root_width"], p["petal_width"], length)
    t = _thickness(name, size, thickness, curved_default=0.1)
    outline, traced = _polar_outline(body, 2 * length, angles)
    design = _Design(name, body, [outline], [], t, _bowl(p["base_radius"], length - p["base_radius"]),
                     float(size[1]) - t, traced=[traced])
    return _finish(_Plate(design, size), np.full(5, length - p["rotor_inset"]), angles, num_sensors)


def make_donut(size, thickness, num_rotors, num_sensors, params) -> Shape:
    """Ring with 4 rotors at 0, 90, 180, 270 deg; no centre IMU: the frame is the average of
    the 4 centre-symmetric ring IMUs, which are also the peripheral ones."""
    name = "donut"
    p = _params(name, params, {"hole_radius": 0.85})
    _count(name, "4 rotors on its ring", 4, num_rotors, "num_rotors")
    _count(name, "4 ring IMUs (their average is its frame)", 4, num_sensors, "num_sensors")
    outer, hole = 0.5 * float(size[0]), p["hole_radius"]
    if not hole < outer:
        raise ValueError(f"{name}: hole_radius {hole} must be < {outer}")

    def ring(q: np.ndarray) -> np.ndarray:
        r = np.hypot(q[:, 0], q[:, 1])
        return (r >= hole) & (r <= outer)
    design = _Design(name, ring, [_circle(outer), _circle(hole)[::-1]], [(0.0, 0.0)],
                     _thickness(name, size, thickness),
                     traced=[_circle(outer, 1e-3), _circle(hole, 1e-3)[::-1]])
    return _finish(_Plate(design, size), np.full(4, 0.5 * (outer + hole)), _angles(4), num_sensors,
                   ring_frame=True)


def make_leaf(size, thickness, num_rotors, num_sensors, params) -> Shape:
    """Pointed ellipse, long along Z (half-width (x/2)(1 - (2z / z_size)^2)); 4 rotors, two
    on the midrib and two at the widest points."""
    name = "leaf"
    p = _params(name, params, {"rotor_x": 0.75, "rotor_z": 1.55})
    _count(name, "4 rotors", 4, num_rotors, "num_rotors")
    half_w, half_l = 0.5 * float(size[0]), 0.5 * float(size[2])

    def blade(q: np.ndarray) -> np.ndarray:
        return np.abs(q[:, 0]) <= half_w * (1 - np.minimum((q[:, 1] / half_l) ** 2, 1))
    outline, traced = _polar_outline(blade, 2 * max(half_w, half_l), _angles(4))
    design = _Design(name, blade, [outline], [], _thickness(name, size, thickness), traced=[traced])
    radii = np.array([p["rotor_x"], p["rotor_z"], p["rotor_x"], p["rotor_z"]])
    return _finish(_Plate(design, size), radii, _angles(4), num_sensors)


SHAPES: dict[str, Callable[..., Shape]] = {
    "donut": make_donut,
    "star": make_star,
    "flower": make_flower,
    "leaf": make_leaf,
    "octopus": make_octopus,
    "orange_peel": make_orange_peel,
}
