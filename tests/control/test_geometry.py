"""rigid_body: mass, centre of mass, inertia and rotor geometry of a mesh against the closed
forms of a uniform box, and their independence of where and how the body sits."""
import numpy as np
import pytest

from sdexp.sim.drone import RotorPatches
from sdexp.sim.mesh.surface import boundary_faces
from sdexp.sim.physics.fem import build_fem
from sdexp.sim.rigid.geometry import rigid_body, rotation_2d
from sdexp.sensing.rotations import matrix_from_euler
from sdexp.sim.mesh.structured import box_tets, box_tris

LENGTHS = (2.0, 0.4, 1.0)
ORIGIN = np.array([1.0, 2.0, -3.0])          # box corner; the centre is ORIGIN + LENGTHS / 2
MASS = 1.7


def outward_normals(points, faces):
    if faces.shape[1] == 3:
        a, b, c = (points[faces[:, k]] for k in range(3))
        return np.cross(b - a, c - a)
    d = points[faces[:, 1]] - points[faces[:, 0]]
    return np.c_[d[:, 1], -d[:, 0]]


def patches(points, boundary, specs):
    """Hand-made RotorPatches: for each (anchor, normal, half-widths) the boundary faces facing
    ``normal`` whose centroid lies within the box anchor +- half (equal vertex weights)."""
    n = outward_normals(points, boundary)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    cen = points[boundary].mean(axis=1)
    face_lists, vert_lists = [], []
    for anchor, normal, half in specs:
        pick = (n @ normal > 0.99) & np.all(np.abs(cen - anchor) <= half, axis=1)
        assert pick.any()
        face_lists.append(boundary[pick])
        vert_lists.append(np.unique(boundary[pick]))
    faces = np.concatenate(face_lists)
    if faces.shape[1] == 2:
        faces = np.c_[faces, faces[:, :1]]       # the (k, 3) layout build_rotors uses in 2D
    ptr = lambda lists: np.concatenate([[0], np.cumsum([len(x) for x in lists])]).astype(np.int64)
    return RotorPatches(ptr(face_lists), faces.astype(np.int64), ptr(vert_lists),
                        np.concatenate(vert_lists).astype(np.int64),
                        np.concatenate([np.full(len(v), 1.0 / len(v)) for v in vert_lists]),
                        np.array([a for a, _, _ in specs]), np.array([n for _, n, _ in specs], dtype=float))


def box3d(k):
    counts = (8 * k, 2 * k, 4 * k)
    pts, tets = box_tets(counts, LENGTHS, tuple(ORIGIN))
    mass = build_fem(pts, tets, MASS, 1e4, 0.3).mass
    h = np.array(LENGTHS) / counts
    c = ORIGIN + np.array(LENGTHS) / 2
    top = c[1] + LENGTHS[1] / 2
    # rotor 0 on the top face at (c_x + 0.5, c_z): the 2 x 2 cells around that grid vertex;
    # rotor 1 on the +x end face at its centre
    specs = [(np.array([c[0] + 0.5, top, c[2]]), np.array([0.0, 1.0, 0.0]), np.array([h[0], 1e-9, h[2]])),
             (np.array([c[0] + 1.0, c[1], c[2]]), np.array([1.0, 0.0, 0.0]), np.array([1e-9, h[1], h[2]]))]
    return pts, mass, patches(pts, boundary_faces(tets), specs)


def box_inertia(m, a, b, c):
    return m / 12 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])


def test_box_mass_com_and_rotors_are_exact():
    pts, mass, rotors = box3d(1)
    M, com, J, pos, dirs = rigid_body(pts, mass, rotors, np.eye(3))
    assert M == pytest.approx(MASS, rel=1e-12)
    # the Kuhn triangulation is point-symmetric, so lumping keeps the centre exact
    np.testing.assert_allclose(com, ORIGIN + np.array(LENGTHS) / 2, atol=1e-12)
    np.testing.assert_allclose(pos, [[0.5, LENGTHS[1] / 2, 0.0], [LENGTHS[0] / 2, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(dirs, [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], atol=1e-12)
    # symmetric positive definite, and satisfying the triangle inequality of inertia tensors
    np.testing.assert_allclose(J, J.T, atol=1e-15)
    lam = np.linalg.eigvalsh(J)
    assert lam.min() > 0 and lam[2] <= lam[0] + lam[1]


def test_lumped_inertia_converges_to_the_uniform_box():
    exact = box_inertia(MASS, *LENGTHS)
    errors, products = [], []
    for k in (1, 2, 4):
        pts, mass, rotors = box3d(k)
        J = rigid_body(pts, mass, rotors, np.eye(3))[2]
        errors.append(np.abs(np.diag(J) - np.diag(exact)) / np.diag(exact))
        products.append(np.abs(J - np.diag(np.diag(J))).max() / np.diag(exact).min())
    errors = np.array(errors)
    # the Kuhn cubes lump more mass on one diagonal: spurious products of inertia, which vanish
    # under refinement (the box's principal axes are x, y, z)
    assert products[0] > products[1] > products[2] and products[2] < 0.02, products
    # every axis improves with each refinement, and is within 2 % at the finest level
    assert np.all(np.diff(errors, axis=0) < 0), errors
    assert errors[-1].max() < 0.02, errors
    # lumping to vertices overestimates the spread of the mass (O(h^2): about 4x per halving)
    assert np.all((errors[0] / errors[1] > 3.5) & (errors[1] / errors[2] > 3.5))


def test_body_quantities_do_not_depend_on_the_pose():
    pts, mass, rotors = box3d(1)
    ref = rigid_body(pts, mass, rotors, np.eye(3))
    R = matrix_from_euler(np.array([0.4, -1.2, 0.7]))
    t = np.array([-5.0, 3.0, 0.5])
    moved = pts @ R.T + t
    M, com, J, pos, dirs = rigid_body(moved, mass, rotors, R)
    assert M == pytest.approx(ref[0])
    np.testing.assert_allclose(com, R @ ref[1] + t, atol=1e-12)
    for got, want in zip((J, pos, dirs), ref[2:]):
        np.testing.assert_allclose(got, want, atol=1e-12)
    # seen from the world frame instead, the same body has the rotated inertia and directions
    _, _, Jw, posw, dirsw = rigid_body(moved, mass, rotors, np.eye(3))
    np.testing.assert_allclose(Jw, R @ ref[2] @ R.T, atol=1e-12)
    np.testing.assert_allclose(dirsw, ref[4] @ R.T, atol=1e-12)
    np.testing.assert_allclose(posw, ref[3] @ R.T, atol=1e-12)
    assert not np.allclose(Jw, ref[2], atol=1e-3)


def test_bent_rotor_patch_tilts_its_thrust():
    """Lift the +x half of the box's top by rotating it about z: the rotor there turns with it."""
    pts, mass, rotors = box3d(1)
    c = ORIGIN + np.array(LENGTHS) / 2
    a = np.deg2rad(20.0)
    Rz = matrix_from_euler(np.array([0.0, 0.0, a]))
    bent = pts.copy()
    hinge = np.array([c[0] + 0.25, c[1] + LENGTHS[1] / 2, 0.0])     # a line along z on the top face
    far = pts[:, 0] > hinge[0] - 1e-9
    bent[far] = (pts[far] - hinge) @ Rz.T + hinge
    dirs = rigid_body(bent, mass, rotors, np.eye(3))[4]
    np.testing.assert_allclose(dirs[0], [-np.sin(a), np.cos(a), 0.0], atol=1e-12)
    np.testing.assert_allclose(dirs[1], [np.cos(a), np.sin(a), 0.0], atol=1e-12)


def box2d(k, a=3.0, b=0.5):
    counts = (6 * k, k)
    pts, tris = box_tris(counts, (a, b), (-1.0, 4.0))
    mass = build_fem(pts, tris, MASS, 1e4, 0.3).mass
    h = np.array([a, b]) / counts
    top = np.array([-1.0 + a / 2 + 1.0, 4.0 + b])
    rotors = patches(pts, boundary_faces(tris), [(top, np.array([0.0, 1.0]), np.array([h[0], 1e-9]))])
    return pts, mass, rotors


def test_2d_polar_inertia_and_rotor():
    a, b = 3.0, 0.5
    exact = MASS / 12 * (a * a + b * b)
    errors = []
    for k in (1, 2, 4):
        pts, mass, rotors = box2d(k, a, b)
        M, com, J, pos, dirs = rigid_body(pts, mass, rotors, np.eye(2))
        assert J.shape == (1, 1) and M == pytest.approx(MASS)
        errors.append(abs(J[0, 0] - exact) / exact)
        np.testing.assert_allclose(pos, [[1.0, b / 2]], atol=1e-12)
        np.testing.assert_allclose(dirs, [[0.0, 1.0]], atol=1e-12)
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.02, errors
    # pose independence in 2D
    pts, mass, rotors = box2d(2, a, b)
    ref = rigid_body(pts, mass, rotors, np.eye(2))
    R = rotation_2d(2.5)
    M, com, J, pos, dirs = rigid_body(pts @ R.T + [3.0, -1.0], mass, rotors, R)
    np.testing.assert_allclose(com, R @ ref[1] + [3.0, -1.0], atol=1e-12)
    for got, want in zip((J, pos, dirs), ref[2:]):
        np.testing.assert_allclose(got, want, atol=1e-12)


def test_rotation_2d_is_counterclockwise():
    np.testing.assert_allclose(rotation_2d(np.pi / 2) @ [1.0, 0.0], [0.0, 1.0], atol=1e-15)
    R = rotation_2d(0.7)
    np.testing.assert_allclose(R.T @ R, np.eye(2), atol=1e-15)
    # the 2D rotation is the 3D one about z
    np.testing.assert_allclose(matrix_from_euler(np.array([0.0, 0.0, 0.7]))[:2, :2], R, atol=1e-15)
