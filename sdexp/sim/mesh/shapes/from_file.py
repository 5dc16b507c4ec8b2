"""A drone of one's own: its body from ``drone.mesh.file``, its rotors where ``drone.rotors``
lists them, its IMUs by the placement rule (supplement D) unless ``drone.imus`` lists them.

Rotors are snapped onto the nearest surface facing their normal (``drone.rotor_normals``,
default +Y), which is how the built-in drones' rotors sit: on the surface, pushing along its
normal. The root of the sensor tree is the body's centroid; the frame IMU sits on the upper
surface straight above it, and the rule's IMUs straight above their tree points, as for the
built-in drones.
"""
from __future__ import annotations

import numpy as np

from sdexp.config import MAX_ELEMENTS, check_range
from sdexp.errors import UserError
from sdexp.sim.mesh.meshfile import read_body
from sdexp.sim.mesh.placement import closest_gap, most_imus, tree_imus
from sdexp.sim.mesh.shape import Shape
from sdexp.sim.mesh.shapes.shapes2d import lift as lift2
from sdexp.sim.mesh.snap import lift3, patch_normal, snap
from sdexp.sim.mesh.surface import enclosed_centroid, encloses


def _listed(cfg, key: str, values, normals, radius: float, body) -> tuple[np.ndarray, np.ndarray]:
    up = np.eye(body.dim)[1]
    values = [[float(x) for x in p] for p in values]     # config lists (ListConfig in validate())
    normals = [[float(x) for x in n] for n in normals]
    anchors, out = [], []
    for k, p in enumerate(values):
        n = np.asarray(normals[k]) if normals else up
        n = n / np.linalg.norm(n)
        anchor, normal, dist = snap(body.vertices, body.faces, np.asarray(p), n, radius)
        if dist > radius:
            where = "no surface faces that way" if not np.isfinite(dist) else f"the nearest surface facing " \
                f"{n.round(3).tolist()} is {dist:.3g} m away"
            side = "inside" if encloses(body.vertices, body.faces, np.asarray(p)) else "off"
            raise UserError(f"drone.{key}[{k}] = {p} is {side} the body of {cfg.mesh.file}: {where}; "
                            f"allowed within drone.{'imu' if key == 'imus' else 'rotor'}_radius = {radius:g} m of its surface")
        anchors.append(anchor)
        out.append(n if normals else normal)   # a listed normal is the thrust direction as given
    return np.array(anchors).reshape(-1, body.dim), np.array(out).reshape(-1, body.dim)


def _lifted(body, planar: np.ndarray, what: str, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Planar points (x, z) / (x, y) straight up onto the upper surface, with its normals."""
    planar = np.atleast_2d(planar)
    if body.dim == 2:
        try:
            return lift2(body.vertices, body.faces, planar)
        except ValueError:
            bad = planar[:, 0].round(3).tolist()
    else:
        points = [lift3(body.vertices, body.faces, q) for q in planar]
        if all(p is not None for p in points):
            up = np.array([0.0, 1.0, 0.0])
            normals = [patch_normal(body.vertices, body.faces, p, up, cfg.imu_radius) for p in points]
            return np.array(points), np.array(normals)
        bad = [q.round(3).tolist() for q, p in zip(planar, points) if p is None]
    raise UserError(f"drone.num_sensors = {cfg.num_sensors}: the placement rule puts the {what} at {bad}, "
                    f"where {cfg.mesh.file} has no upper surface; list them in drone.imus "
                    f"(positions on the body) or change drone.rotors")


def _spaced(cfg, center: np.ndarray, rotors: np.ndarray, tree: np.ndarray) -> None:
    """The rule's IMUs at least drone.imu_radius apart (and from the frame IMU), as the paper's 3D
    designs' are (3.8 radii or more): closer, their patches bind the same faces and read one bend."""
    gap = closest_gap(center, tree)
    if gap < cfg.imu_radius:
        most = most_imus(center, rotors, int(cfg.num_sensors), cfg.imu_radius, root_radius=float(cfg.rotor_radius))
        raise UserError(f"drone.num_sensors = {cfg.num_sensors}: the placement rule puts IMUs {gap:.3g} m apart on "
                        f"{cfg.mesh.file}, closer than drone.imu_radius = {cfg.imu_radius:g} m; allowed at most "
                        f"{most} on these rotors, or list them in drone.imus")


def make_file_shape(cfg) -> Shape:
    """The Shape of a drone from a mesh file (cfg: a validated DroneConfig with drone.mesh.file)."""
    body = read_body(cfg.mesh.file, cfg.dim, cfg.mesh.scale)
    rotors, rotor_normals = _listed(cfg, "rotors", cfg.rotors, cfg.rotor_normals, cfg.rotor_radius, body)
    if cfg.dim == 3 and np.linalg.matrix_rank(rotors[1:] - rotors[0], tol=1e-3 * body.extent.max()) < 2:
        raise UserError(f"drone.rotors = {np.round(rotors, 3).tolist()} lie on one line: a 3D drone needs three "
                        "not in a line, or it cannot hold its attitude")
    center = enclosed_centroid(body.vertices, body.faces)
    planar = [0, 2] if cfg.dim == 3 else [0]
    frame, frame_normals = _lifted(body, center[None][:, planar] if cfg.dim == 3 else center[None],
                                   "frame IMU (over the centroid)", cfg)
    if cfg.imus:
        imus, imu_normals = _listed(cfg, "imus", cfg.imus, [], cfg.imu_radius, body)
    elif cfg.num_sensors:
        try:
            tree = tree_imus(center, rotors, int(cfg.num_sensors), root_radius=float(cfg.rotor_radius))
        except ValueError as err:
            raise UserError(f"drone.num_sensors = {cfg.num_sensors}: {err}; list them in drone.imus") from None
        _spaced(cfg, center, rotors, tree)
        imus, imu_normals = _lifted(body, tree, "peripheral IMUs", cfg)
    else:
        imus, imu_normals = np.zeros((0, cfg.dim)), np.zeros((0, cfg.dim))
    return Shape(dim=cfg.dim, vertices=body.vertices, faces=body.faces, holes=body.holes, center=center,
                 rotors=rotors, rotor_normals=rotor_normals, imus=imus, imu_normals=imu_normals,
                 frame_imus=frame, frame_normals=frame_normals,
                 volume_mesh=None if body.elems is None else (body.vertices, body.elems))


# A drone from a mesh file, longest side (m): sdexp's drones span 1.1-8 m; far outside this
# range the file's unit is not the one drone.mesh.scale says (mm read as m is 1000x).
FILE_EXTENT = (0.05, 50.0)
MIN_ROTORS = {2: 2, 3: 3}   # thrust and the tilt(s): one rotor per controlled degree of freedom


def check_file_drone(d) -> tuple[list[float], int | None]:
    """The checks of a drone from drone.mesh.file before anything is meshed (the file is read:
    sdexp.sim.mesh.meshfile): its listed rotors and IMUs, its scale, its size. Returns the
    body's bounding lengths and, for a volume mesh given as such, its element count."""
    def need(ok: bool, message: str) -> None:
        if not ok:
            raise UserError(message)

    check_range(d.mesh.scale > 0, "drone.mesh.scale", d.mesh.scale, "> 0 (the file's unit in metres)")
    need(not d.mesh.mirror and d.mesh.layers == 0, "drone.mesh.mirror and drone.mesh.layers: allowed [] and 0 for a "
         "drone from drone.mesh.file (fTetWild or Triangle meshes the file's body whole)")
    dims = f"[x, y{', z' if d.dim == 3 else ''}]"
    for key in ("rotors", "rotor_normals", "imus"):
        rows = [list(r) for r in getattr(d, key)]
        need(all(len(r) == d.dim for r in rows), f"drone.{key} = {rows}: allowed {dims} rows ({d.dim}D drone)")
    for k, n in enumerate(d.rotor_normals):   # before the counts: a zero normal is wrong whatever their number
        need(any(float(x) != 0 for x in n), f"drone.rotor_normals[{k}] = {list(n)} is zero: allowed a non-zero "
             "direction (the rotor's thrust), one per rotor, or [] for +Y")
    need(len(d.rotors) >= MIN_ROTORS[d.dim], f"drone.rotors lists {len(d.rotors)}: a {d.dim}D drone needs at least "
         f"{MIN_ROTORS[d.dim]} rotors (its thrust and its tilt" + (" about two axes)" if d.dim == 3 else ")"))
    need(len(d.rotors) == d.num_rotors, f"drone.num_rotors = {d.num_rotors} but drone.rotors lists "
         f"{len(d.rotors)}: allowed {len(d.rotors)}")
    need(not d.rotor_normals or len(d.rotor_normals) == len(d.rotors), f"drone.rotor_normals lists "
         f"{len(d.rotor_normals)}: allowed [] (+Y) or one per rotor ({len(d.rotors)})")
    need(not d.imus or len(d.imus) == d.num_sensors, f"drone.imus lists {len(d.imus)}: allowed [] (the placement "
         f"rule) or one per peripheral IMU (drone.num_sensors = {d.num_sensors})")
    body = read_body(d.mesh.file, d.dim, d.mesh.scale)
    size = [float(x) for x in body.extent]
    lo, hi = FILE_EXTENT
    need(lo <= max(size) <= hi, f"drone.mesh.scale = {d.mesh.scale:g} makes the body of {d.mesh.file} "
         f"{max(size):.4g} m across: allowed {lo:g} to {hi:g} m (0.001 reads a file in millimetres)")
    need(not list(d.size) or (len(d.size) == d.dim and all(abs(a - b) <= 0.01 * b for a, b in zip(d.size, size))),
         f"drone.size = {list(d.size)}: allowed [] for a drone from drone.mesh.file (its size is the file's, "
         f"{[round(x, 4) for x in size]} m)")
    if body.elems is not None:
        need(len(body.elems) <= MAX_ELEMENTS, f"drone.mesh.file = {d.mesh.file}: a volume mesh of "
             f"{len(body.elems):,} elements; allowed at most about {MAX_ELEMENTS:,}")
    # rotors and IMUs onto the body now, not after the run folder and the mesh are made (numpy only)
    make_file_shape(d)
    return size, None if body.elems is None else len(body.elems)
