"""The six 2D drones of supplement B (table "2D models"): outlines, rotors and IMUs.

The paper's figure of these drones is not available, so the outlines are drawn from their
names and the table's bounding lengths. Every drone lies in the X-Y plane, +Y up, with its
bounding box centred at the origin. The outer boundary runs counter-clockwise and holes
clockwise, so the body is always on the left of a segment and its outward normal is the
segment direction turned clockwise.

Rotors sit on the upper boundary (the part of the outline facing +Y) and push along its outward
normal. Peripheral IMUs come from the placement rule in :mod:`sdexp.sim.mesh.placement`; the rule
yields points on the sensor tree, which usually lie inside the body, so each is moved along +Y
onto the upper boundary, keeping its x coordinate.
"""
from __future__ import annotations

from typing import Callable

import contourpy
import numpy as np

from sdexp.sim.mesh.placement import tree_imus
from sdexp.sim.mesh.shape import Shape
from sdexp.sim.mesh.surface import enclosed_centroid

# Sensor-tree root radius (m): merges a rotor right above the centre with the root, as the rod's
# middle rotor is, instead of making it a node with a near-zero edge.
ROOT_RADIUS = 0.1
# Boundary resolution of curved outlines, as a fraction of the larger bounding length; the
# mesher refines further, but it cannot make a polygon rounder than this.
OUTLINE_STEP = 0.025
# Grid cells per larger bounding length when tracing organic outlines from primitives.
TRACE_CELLS = 600


def _arc(radius, a0, a1, step):
    """Points on a circle about the origin from angle a0 to a1 (degrees), both ends included."""
    t0, t1 = np.radians([a0, a1])
    pieces = max(1, int(np.ceil(abs(t1 - t0) * radius / step)))
    t = np.linspace(t0, t1, pieces + 1)
    return radius * np.column_stack([np.cos(t), np.sin(t)])


# Implicit primitives for organic outlines: negative inside. A union is their minimum, and only
# the sign matters, so the functions need not be exact distances.
def _ellipse(cx, cy, rx, ry):
    return lambda x, y: (np.hypot((x - cx) / rx, (y - cy) / ry) - 1.0) * min(rx, ry)


def _box(x0, y0, x1, y1):
    def f(x, y):
        dx = np.maximum(x0 - x, x - x1)
        dy = np.maximum(y0 - y, y - y1)
        return np.hypot(np.maximum(dx, 0), np.maximum(dy, 0)) + np.minimum(np.maximum(dx, dy), 0)
    return f


def _band(points, r0, r1):
    """A bent limb: a polyline with round ends whose half-width tapers from r0 to r1."""
    pts = np.asarray(points, dtype=float)
    lengths = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(lengths)]) / lengths.sum()

    def f(x, y):
        best = np.inf
        for a, b, sa, sb in zip(pts[:-1], pts[1:], s[:-1], s[1:]):
            d = b - a
            t = np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / (d @ d), 0, 1)
            r = r0 + (r1 - r0) * (sa + t * (sb - sa))
            best = np.minimum(best, np.hypot(x - a[0] - t * d[0], y - a[1] - t * d[1]) - r)
        return best
    return f


def _trace(name, primitives, box, symmetric=False):
    """Counter-clockwise outline of the union of primitives drawn about ``box`` (x0, y0, x1,
    y1), resampled to OUTLINE_STEP. ``symmetric``: the primitives are mirror images about
    x = 0, and so is the outline returned (the tracing grid alone would break the symmetry)."""
    x0, y0, x1, y1 = box
    lx, ly = x1 - x0, y1 - y0
    h = max(lx, ly) / TRACE_CELLS
    xs = np.arange(x0 - 0.2 * lx, x1 + 0.2 * lx + h, h)
    ys = np.arange(y0 - 0.2 * ly, y1 + 0.2 * ly + h, h)
    x, y = np.meshgrid(xs, ys)
    z = np.min([f(x, y) for f in primitives], axis=0)
    tracer = contourpy.contour_generator(xs, ys, z, line_type=contourpy.LineType.Separate)
    lines = tracer.lines(0.0)
    if len(lines) != 1:
        raise ValueError(f"{name}: these params split the outline into {len(lines)} pieces; "
                         "the body must be one region without holes")
    line = lines[0] if _ring_area(lines[0]) > 0 else lines[0][::-1]
    closed = line if np.allclose(line[0], line[-1]) else np.vstack([line, line[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    n = int(np.ceil(arc[-1] / (OUTLINE_STEP * max(lx, ly)) / 2)) * 2
    start = 0.0
    if symmetric:
        # Start on the axis at the bottom, so point i and point n - i are mirror images.
        a, b = closed[:-1], closed[1:]
        cross = np.flatnonzero((a[:, 0] < 0) != (b[:, 0] < 0))
        t = a[cross, 0] / (a[cross, 0] - b[cross, 0])
        k = np.argmin(a[cross, 1] + t * (b[cross, 1] - a[cross, 1]))
        start = arc[cross[k]] + t[k] * (arc[cross[k] + 1] - arc[cross[k]])
    s = np.mod(start + np.linspace(0.0, arc[-1], n, endpoint=False), arc[-1])
    ring = np.column_stack([np.interp(s, arc, closed[:, 0]), np.interp(s, arc, closed[:, 1])])
    if symmetric:
        ring = (ring + ring[-np.arange(n)] * [-1.0, 1.0]) / 2
    return ring


def _ring_area(ring):
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def _segments(rings):
    vertices, segments, offset = [], [], 0
    for ring in rings:
        k = len(ring)
        vertices.append(ring)
        segments.append(offset + np.column_stack([np.arange(k), (np.arange(k) + 1) % k]))
        offset += k
    return np.vstack(vertices).astype(float), np.vstack(segments).astype(np.int32)


def _upper_exits(vertices, segments, x):
    """Where the vertical line at x leaves the body upwards: sorted heights and outward normals.

    At a vertex the normals of the two segments meeting there are averaged, the way the
    simulator averages the segments around a rotor.
    """
    a, b = vertices[segments[:, 0]], vertices[segments[:, 1]]
    d = b - a
    normal = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    tol = 1e-12 * (np.ptp(vertices[:, 0]) + np.ptp(vertices[:, 1]))
    # With the body on the left, exactly the segments running towards -X face up.
    hit = (d[:, 0] < 0) & (b[:, 0] - tol <= x) & (x <= a[:, 0] + tol)
    t = np.clip((x - a[hit, 0]) / d[hit, 0], 0.0, 1.0)
    heights = a[hit, 1] + t * d[hit, 1]
    normals = normal[hit]
    order = np.argsort(heights, kind="stable")
    exits = []
    for y, n in zip(heights[order], normals[order]):
        if exits and y - exits[-1][0] <= tol:
            exits[-1][1] = exits[-1][1] + n
        else:
            exits.append([y, n])
    return [(y, n / np.linalg.norm(n)) for y, n in exits]


def lift(vertices, segments, points):
    """Move each point along +Y to the top of the body column it is in (or the nearest one
    below it when it is above the body) and return those points with their outward normals."""
    out, normals = [], []
    for px, py in points:
        exits = _upper_exits(vertices, segments, px)
        if not exits:
            raise ValueError(f"x = {px:.3f} is outside the drone's width")
        above = [e for e in exits if e[0] >= py]
        y, n = above[0] if above else exits[-1]
        out.append((px, y))
        normals.append(n)
    return np.array(out, dtype=float).reshape(-1, 2), np.array(normals, dtype=float).reshape(-1, 2)


def _read_params(name, params, defaults):
    known = {**defaults, "root_radius": ROOT_RADIUS}
    given = dict(params or {})
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ValueError(f"{name}: unknown params {unknown}; known params are {sorted(known)}")
    return {k: float(given.get(k, v)) for k, v in known.items()}


def _check(ok, name, what):
    if not ok:
        raise ValueError(f"{name}: {what}")


def _generator(name: str, defaults: dict, outline: Callable) -> Callable[..., Shape]:
    """Wrap ``outline(lx, ly, num_rotors, params) -> (rings, hole_points, rotor_x)`` into a
    Shape generator. ``rings`` may be drawn anywhere at about the right size: they are fitted
    to the bounding lengths, and ``hole_points`` and the rotors' x coordinates follow them."""

    def make(size, thickness, num_rotors, num_sensors, params=None) -> Shape:
        # ``thickness`` is the out-of-plane depth of a plane-strain body: the outline does not
        # depend on it.
        size = [float(s) for s in size]
        _check(len(size) == 2 and min(size) > 0, name, f"size = {size}: need two lengths > 0")
        _check(num_rotors >= 1, name, f"num_rotors = {num_rotors}: need at least 1")
        _check(num_sensors >= 0, name, f"num_sensors = {num_sensors}: need at least 0")
        lx, ly = size
        p = _read_params(name, params, defaults)
        rings, hole_points, rotor_x = outline(lx, ly, int(num_rotors), p)
        pts = np.vstack(rings)
        mid = (pts.min(axis=0) + pts.max(axis=0)) / 2
        scale = np.array([lx, ly]) / np.ptp(pts, axis=0)
        vertices, segments = _segments([(r - mid) * scale for r in rings])
        holes = (np.asarray(hole_points, dtype=float).reshape(-1, 2) - mid) * scale
        rotor_x = (np.asarray(rotor_x, dtype=float) - mid[0]) * scale[0]
        # From above the drone: rotors go on the topmost boundary at their x.
        rotors, rotor_normals = lift(vertices, segments, [(x, np.inf) for x in rotor_x])
        center = enclosed_centroid(vertices, segments)
        try:
            tree = tree_imus(center, rotors, int(num_sensors), p["root_radius"])
        except ValueError as err:
            raise ValueError(f"{name}: cannot place num_sensors = {num_sensors}: {err}") from None
        imus, imu_normals = lift(vertices, segments, tree)
        frame_imus, frame_normals = lift(vertices, segments, center[None])
        return Shape(dim=2, vertices=vertices, faces=segments, holes=holes, center=center,
                     rotors=rotors, rotor_normals=rotor_normals, imus=imus,
                     imu_normals=imu_normals, frame_imus=frame_imus, frame_normals=frame_normals)

    make.__name__ = make.__qualname__ = f"make_{name}"
    make.__doc__ = outline.__doc__
    return make


def _spread(n, lo, hi):
    """n evenly spaced positions from lo to hi, or the middle for a single one."""
    return np.array([(lo + hi) / 2]) if n == 1 else np.linspace(lo, hi, n)


def _engine(lx, ly, n, p):
    """Inline engine seen from the side: an oil sump under the crankcase and a row of cylinder
    heads separated by deep bays. Rotors share the cylinder heads' tops evenly, so their count
    must be a multiple of the number of cylinders."""
    cylinders = int(p["cylinders"])
    _check(cylinders >= 1 and cylinders == p["cylinders"], "engine",
           f"cylinders = {p['cylinders']}: need a whole number >= 1")
    _check(n % cylinders == 0, "engine",
           f"num_rotors = {n} cannot be shared evenly by {cylinders} cylinder heads")
    bay, depth, sump = p["bay_width"] * lx, p["bay_depth"] * ly, p["sump_height"] * ly
    width = (lx - (cylinders - 1) * bay) / cylinders
    _check(width > 0 and depth > 0 and sump > 0 and depth + sump < ly, "engine",
           "bay_width, bay_depth and sump_height leave no crankcase")
    _check(0 < p["sump_bottom"] <= p["sump_top"] <= 1, "engine",
           "need 0 < sump_bottom <= sump_top <= 1")
    lefts = [-lx / 2 + k * (width + bay) for k in range(cylinders)]
    top = []
    for k in reversed(range(cylinders)):
        top += [(lefts[k] + width, ly), (lefts[k], ly)]
        if k:
            top += [(lefts[k], ly - depth), (lefts[k] - bay, ly - depth)]
    sb, st = p["sump_bottom"] * lx / 2, p["sump_top"] * lx / 2
    ring = [(-sb, 0), (sb, 0), (st, sump), (lx / 2, sump), *top, (-lx / 2, sump), (-st, sump)]
    per = n // cylinders
    rotor_x = [x0 + width * (j + 0.5) / per for x0 in lefts for j in range(per)]
    return [np.array(ring, dtype=float)], np.zeros((0, 2)), rotor_x


def _bunny(lx, ly, n, p):
    """Sitting bunny seen from the front: round body, head, two long ears. Rotors: the head top
    (1), the shoulders (2), or both (3)."""
    _check(n <= 3, "bunny", f"num_rotors = {n}: the bunny has 3 rotor sites (head top, shoulders)")
    body_h, head_w, head_h = p["body_height"] * ly, p["head_width"] * lx, p["head_height"] * ly
    ear_r, ear_x = p["ear_width"] * lx / 2, p["ear_spacing"] * lx / 2
    # The head sinks a quarter of its height into the body, so the two always join.
    head_y = body_h + head_h / 4
    _check(0 < body_h and head_y + head_h / 2 < ly - 2 * ear_r, "bunny",
           "body_height + head_height leave no room for the ears")
    _check(ear_r < ear_x < head_w / 2, "bunny", "the ears must stand apart on the head")
    ear_tip = (1.15 * ear_x, ly - ear_r)  # splayed slightly outwards
    primitives = [_ellipse(0, body_h / 2, lx / 2, body_h / 2),
                  _ellipse(0, head_y, head_w / 2, head_h / 2),
                  _band([(ear_x, head_y), ear_tip], ear_r, ear_r),
                  _band([(-ear_x, head_y), (-ear_tip[0], ear_tip[1])], ear_r, ear_r)]
    ring = _trace("bunny", primitives, (-lx / 2, 0, lx / 2, ly), symmetric=True)
    shoulder = p["shoulder"] * lx
    _check(head_w / 2 < shoulder < lx / 2, "bunny",
           "shoulder must lie between the head and the side")
    rotor_x = {1: [0.0], 2: [-shoulder, shoulder], 3: [-shoulder, 0.0, shoulder]}[n]
    return [ring], np.zeros((0, 2)), rotor_x


def _diamond(lx, ly, n, p):
    """Cut gem seen from the side: flat table, crown facets down to the widest girdle, pavilion
    tapering to the culet at the bottom, and a rhombic window in the middle. Rotors spread
    evenly over the table and the crown."""
    table, crown = p["table_width"] * lx / 2, p["crown_height"] * ly
    _check(0 < table < lx / 2 and 0 < crown < ly, "diamond",
           "need 0 < table_width < 1 and 0 < crown_height < 1")
    girdle = ly - crown
    outer = np.array([(0, 0), (lx / 2, girdle), (table, ly), (-table, ly), (-lx / 2, girdle)],
                     dtype=float)
    rings = [outer]
    holes = np.zeros((0, 2))
    if p["hole_size"] > 0:
        # Centred on the outline's centroid, so the window leaves the centre where it was.
        cx, cy = enclosed_centroid(*_segments([outer]))
        hw, hh = p["hole_size"] * lx / 2, p["hole_size"] * ly / 2
        hole = np.array([(cx, cy + hh), (cx + hw, cy), (cx, cy - hh), (cx - hw, cy)])
        # Keep a rim at least half the window's size: the window grown by half stays inside.
        grown = (hole - [cx, cy]) * 1.5 + [cx, cy]
        edges = np.roll(outer, -1, axis=0) - outer
        rel = grown[:, None, :] - outer[None]
        _check(np.all(edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0] > 0),
               "diamond", f"hole_size = {p['hole_size']} leaves too thin a rim")
        rings.append(hole)
        holes = np.array([[cx, cy]])
    span = p["rotor_span"] * lx / 2
    _check(0 <= span < lx / 2, "diamond", "need 0 <= rotor_span < 1")
    return rings, holes, _spread(n, -span, span)


def _elephant(lx, ly, n, p):
    """Elephant seen from the side, facing +X: body, head, a curled trunk, two legs and a
    tail. Rotors spread evenly along the top, from the back onto the head."""
    legs, leg_w, trunk = p["leg_height"] * ly, p["leg_width"] * lx, p["trunk_width"] * lx
    _check(0 < legs < 0.45 * ly and 0 < leg_w < 0.15 * lx and 0 < trunk < 0.1 * lx, "elephant",
           "need 0 < leg_height < 0.45, 0 < leg_width < 0.15, 0 < trunk_width < 0.1")
    # Behind 0.15 the back slopes down to the tail; beyond 0.85 the head falls to the trunk.
    _check(0.15 <= p["back_start"] <= p["back_end"] <= 0.85, "elephant",
           "need 0.15 <= back_start <= back_end <= 0.85")
    u = lambda a, b: (a * lx, b * ly)  # noqa: E731  (points as fractions of the bounding box)
    body_y, body_ry = (legs + 0.8 * ly) / 2, (0.8 * ly - legs) / 2
    primitives = [
        _ellipse(0.42 * lx, body_y, 0.31 * lx, body_ry),
        _ellipse(*u(0.76, 0.75), 0.13 * lx, 0.25 * ly),
        # Legs reach up to the body's mid-height so they join it whatever leg_height is.
        _box(0.18 * lx, 0, 0.18 * lx + leg_w, body_y),
        _box(0.52 * lx, 0, 0.52 * lx + leg_w, body_y),
        _band([u(0.82, 0.7), u(0.9, 0.45), u(0.92, 0.2), u(0.96, 0.07), u(0.99, 0.14)],
              trunk / 2, trunk / 4),
        _band([u(0.14, 0.62), u(0.06, 0.52), u(0.04, 0.42)], 0.02 * lx, 0.015 * lx),
    ]
    ring = _trace("elephant", primitives, (0, 0, lx, ly))
    return [ring], np.zeros((0, 2)), _spread(n, p["back_start"] * lx, p["back_end"] * lx)


def _rainbow(lx, ly, n, p):
    """Rainbow: a semicircular band whose two ends carry straight legs down to the table's
    height. Rotors spread over the outer arc between rotor_angle and 180 - rotor_angle degrees
    (a single one sits on the crown)."""
    outer = lx / 2
    inner = outer - p["band_width"] * lx
    legs = ly - outer
    _check(0 < inner < outer, "rainbow", "need 0 < band_width < 0.5")
    _check(legs >= 0, "rainbow", f"size = ({lx}, {ly}): a semicircle needs ly >= lx / 2")
    _check(0 < p["rotor_angle"] <= 90, "rainbow", "need 0 < rotor_angle <= 90 degrees")
    step = OUTLINE_STEP * max(lx, ly)
    foot = np.array([(inner, -legs), (outer, -legs)]) if legs > 0 else np.zeros((0, 2))
    ring = np.vstack([foot, _arc(outer, 0, 180, step), foot[::-1] * [-1, 1],
                      _arc(inner, 180, 0, step)])
    angles = _spread(n, 180 - p["rotor_angle"], p["rotor_angle"])
    return [ring], np.zeros((0, 2)), outer * np.cos(np.radians(angles))


def _rod(lx, ly, n, p):
    """Long rod: a straight beam with rotors spread evenly along its top edge.

    The table gives 0.1 x 8.0 (x by y), but a vertical 8 m rod could not hover on rotors along
    its length; we read it as an 8.0 m long, 0.1 m thick horizontal beam, size = (8.0, 0.1).
    """
    inset = p["rotor_inset"]
    _check(0 < inset < lx / 2, "rod", f"rotor_inset = {inset}: need 0 < rotor_inset < lx / 2")
    ring = np.array([(-lx / 2, -ly / 2), (lx / 2, -ly / 2), (lx / 2, ly / 2), (-lx / 2, ly / 2)])
    return [ring], np.zeros((0, 2)), _spread(n, -lx / 2 + inset, lx / 2 - inset)


SHAPES: dict[str, Callable[..., Shape]] = {
    "engine": _generator("engine", {"cylinders": 3, "bay_width": 0.1, "bay_depth": 0.35,
                                    "sump_height": 0.15, "sump_top": 0.65, "sump_bottom": 0.5},
                         _engine),
    "bunny": _generator("bunny", {"body_height": 0.48, "head_width": 0.56, "head_height": 0.3,
                                  "ear_width": 0.14, "ear_spacing": 0.28, "shoulder": 0.33},
                        _bunny),
    "diamond": _generator("diamond", {"table_width": 0.55, "crown_height": 0.28,
                                      "hole_size": 0.3, "rotor_span": 0.8}, _diamond),
    "elephant": _generator("elephant", {"leg_height": 0.35, "leg_width": 0.14,
                                        "trunk_width": 0.08, "back_start": 0.25,
                                        "back_end": 0.5}, _elephant),
    "rainbow": _generator("rainbow", {"band_width": 0.15, "rotor_angle": 55.0}, _rainbow),
    "rod": _generator("rod", {"rotor_inset": 0.1}, _rod),
}
