"""Mirror-symmetric meshes: mesh one cell of a symmetric design, reflect it across the planes.

fTetWild meshes a symmetric surface into an asymmetric volume (the star's rest vertices miss
their mirror images by 5 cm, a third of an element), and the asymmetry is not harmless: held
under a mirror-symmetric thrust pattern, noise-free, its two folding wings bend 77 and 71 deg
and the body yaws at 1-3 deg/s. No rotor can stop that: the paper's counter-rotating rotor
pairs make no yaw torque, so the yaw of a soft multicopter is steered only by its own
deformation. A mesh reflected from one cell is as symmetric as the design, up to rounding.

``drone.mesh.mirror`` names the planes (x: x = 0, z: z = 0); the shape supplies the cell's
closed surface (``Shape.cell_surface``), fTetWild meshes it, and :func:`reflect` glues each
reflection onto the mesh along the plane.
"""
from __future__ import annotations

import numpy as np

AXES = {"x": 0, "z": 2}


def reflect(points: np.ndarray, elems: np.ndarray, axis: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh (lying on the positive side of coordinate ``axis`` = 0, one face of its
    boundary on that plane) and its reflection across the plane, glued along it.

    The boundary faces facing -axis within ``tol`` of the plane are the cut: their vertices are
    put exactly on the plane (a mesher keeps the cut flat only to its tolerance), shared by both
    halves, so the two halves are conforming by construction. Raises if the cell crosses the
    plane, a vertex move inverts an element, or the glued mesh still has a face on the plane."""
    from sdexp.sim.mesh.surface import boundary_faces, face_normals

    points = np.array(points, dtype=np.float64)
    elems = np.asarray(elems, dtype=np.int64)
    faces = boundary_faces(elems)
    normal = face_normals(points, faces)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    cut = faces[(normal[:, axis] < -0.99) & np.all(np.abs(points[faces][..., axis]) < tol, axis=1)]
    on = np.unique(cut)
    if len(on) == 0:
        raise ValueError(f"no boundary face lies on the mirror plane {'xyz'[axis]} = 0")
    points[on, axis] = 0.0
    off = np.setdiff1d(np.arange(len(points)), on)
    if not np.all(points[off, axis] > 0):
        raise ValueError(f"the cell crosses its mirror plane {'xyz'[axis]} = 0")
    if not np.all(_volumes(points, elems) > 0):
        raise ValueError(f"putting the cut on the plane {'xyz'[axis]} = 0 inverts an element")
    image = np.arange(len(points))
    image[off] = len(points) + np.arange(len(off))
    mirrored = points[off].copy()
    mirrored[:, axis] *= -1.0
    flipped = image[elems]
    flipped[:, [1, 2]] = flipped[:, [2, 1]]   # a reflection turns orientation inside out
    glued_points, glued = np.vstack([points, mirrored]), np.vstack([elems, flipped])
    left = boundary_faces(glued)
    if np.any(np.all(glued_points[left][..., axis] == 0.0, axis=1)):
        raise ValueError(f"the halves do not meet along the whole plane {'xyz'[axis]} = 0")
    return glued_points, np.ascontiguousarray(glued, dtype=np.int32)


def _volumes(points: np.ndarray, elems: np.ndarray) -> np.ndarray:
    d = points[elems[:, 1:]] - points[elems[:, :1]]
    return np.linalg.det(d)


def asymmetric_parts(shape, planes) -> list[str]:
    """The anchor sets of ``shape`` (rotors, IMUs, frame IMUs) that a reflection across one of
    ``planes`` does not map onto themselves: a mirrored mesh would misplace them."""
    bad = []
    for name in planes:
        flip = np.ones(shape.dim)
        flip[AXES[name]] = -1.0
        for part in ("rotors", "imus", "frame_imus"):
            pts = getattr(shape, part)
            d = np.linalg.norm(pts[:, None] * flip - pts[None], axis=2)
            if len(pts) and not np.all(d.min(axis=1) < 1e-6 * max(1.0, np.abs(pts).max())):
                bad.append(f"{part} ({name} = 0)")
    return bad


def symmetric_mesh(cell: tuple[np.ndarray, np.ndarray], planes, mesh_cell) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the cell's closed surface with ``mesh_cell(vertices, faces) -> (points, elems)`` and
    reflect it across each plane in ``planes`` (names in AXES), in order."""
    vertices, faces = cell
    return reflect_all(*mesh_cell(vertices, faces), planes)


def reflect_all(points: np.ndarray, elems: np.ndarray, planes) -> tuple[np.ndarray, np.ndarray]:
    """A cell's mesh reflected across each plane in ``planes`` (names in AXES), in order: the
    elements too, so the whole mesh, not only its nodes, is as symmetric as the design."""
    tol = 1e-2 * float(np.linalg.norm(np.ptp(points, axis=0)))
    for name in planes:
        points, elems = reflect(points, elems, AXES[name], tol)
    return points, elems
