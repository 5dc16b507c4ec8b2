"""Quadratic elements (10-node tets, 6-node triangles) against physics: invariances,
conservation, the patch test, HRZ masses, the cantilever beside linear elements, and the
compiled kernel against its numba reference."""
import numpy as np
import pytest

from sdexp.eval.validate_fem import Beam, FreeBody, cantilever, structured_beam
from sdexp.sim.physics.fem import build_fem, elastic_forces, lame, rest_quaternions, stable_substep
from sdexp.sim.physics.quadratic import QUAD_2D, QUAD_3D, boundary_subfaces, quadratic_mesh
from sdexp.sim.physics.reference import p2_forces_range
from sdexp.sensing.rotations import matrix_from_euler
from sdexp.sim.mesh.structured import box_tets, box_tris


def p2_block(dim, E=5000.0):
    if dim == 3:
        pts, el = box_tets((3, 2, 2), (1.0, 0.4, 0.6), (-0.5, -0.2, -0.3))
    else:
        pts, el = box_tris((4, 2), (1.0, 0.4), (-0.5, -0.2))
    return build_fem(*quadratic_mesh(pts, el), 1.0, E, 0.3)


def rotation(dim, angles=(0.7, -1.2, 0.4)):
    if dim == 3:
        return matrix_from_euler(np.array(angles))
    c, s = np.cos(angles[0]), np.sin(angles[0])
    return np.array([[c, -s], [s, c]])


def converged(fem, x):
    q = rest_quaternions(fem.n_rotations)
    for _ in range(100):  # warm-started polar iterations: converge them fully
        f = elastic_forces(fem, x, q)
    return f


def test_quadratic_mesh_adds_one_shared_node_per_edge():
    pts, el = box_tets((2, 1, 1), (1.0, 0.5, 0.5))
    p2, e2 = quadratic_mesh(pts, el)
    edges = {tuple(sorted(e)) for t in el for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]),
                                                   (t[0], t[3]), (t[1], t[3]), (t[2], t[3]))}
    assert len(p2) == len(pts) + len(edges)
    np.testing.assert_array_equal(e2[:, :4], el)        # corners keep their indices
    for m, (a, b) in enumerate([(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]):   # VTK order
        np.testing.assert_allclose(p2[e2[:, 4 + m]], 0.5 * (p2[e2[:, a]] + p2[e2[:, b]]))


@pytest.mark.parametrize("dim", [2, 3])
def test_hrz_masses_are_positive_and_sum_to_the_mass(dim):
    fem = p2_block(dim)
    assert fem.order == 2 and np.all(fem.mass > 0)
    assert fem.mass.sum() == pytest.approx(1.0, rel=1e-12)
    # one element: corners m/36 and edges 4m/27 (3D), m/19 and 16m/57 (2D)
    pts = np.eye(dim + 1, dim, k=-1)
    p2, e2 = quadratic_mesh(pts, np.arange(dim + 1)[None])
    one = build_fem(p2, e2, 1.0, 1.0, 0.3)
    corner, edge = (1 / 36, 4 / 27) if dim == 3 else (1 / 19, 16 / 57)
    np.testing.assert_allclose(one.mass, np.r_[np.full(dim + 1, corner), np.full(len(p2) - dim - 1, edge)])


@pytest.mark.parametrize("dim", [2, 3])
def test_quadrature_rules_integrate_quadratics_exactly(dim):
    """Degree 2: the mean of L_i L_j over the simplex is (1 + [i = j]) / ((n + 1) (n + 2))."""
    Q = QUAD_3D if dim == 3 else QUAD_2D
    n = dim
    for i in range(n + 1):
        for j in range(n + 1):
            assert np.mean(Q[:, i] * Q[:, j]) == pytest.approx((1 + (i == j)) / ((n + 1) * (n + 2)))


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_motion_produces_no_elastic_force(dim):
    fem = p2_block(dim)
    x = fem.rest @ rotation(dim).T + 3.0
    f = converged(fem, x)
    assert np.abs(f).max() < 1e-9 * fem.mu * np.ptp(fem.rest)


@pytest.mark.parametrize("dim", [2, 3])
def test_forces_rotate_with_the_body_and_carry_no_net_force_or_torque(dim):
    fem = p2_block(dim)
    rng = np.random.default_rng(1)
    x = fem.rest + 0.003 * rng.standard_normal(fem.rest.shape)
    R = rotation(dim, (0.3, 2.0, -0.5))
    f0, f1 = converged(fem, x), converged(fem, x @ R.T)
    np.testing.assert_allclose(f1, f0 @ R.T, atol=1e-9 * np.abs(f0).max())
    assert np.abs(f0.sum(axis=0)).max() < 1e-10 * np.abs(f0).max()
    x3, f3 = (np.pad(a, ((0, 0), (0, 3 - dim))) for a in (x, f0))
    assert np.abs(np.cross(x3, f3).sum(axis=0)).max() < 1e-10 * np.abs(f0).max()


def test_one_rotation_per_element_would_leak_torque():
    """Why quadratic tets rotate at each quadrature point: the rotation of the corner F alone
    leaves a net torque of the order of the strain (here ~1% of the largest nodal force)."""
    fem = p2_block(3)
    x = fem.rest + 0.003 * np.random.default_rng(1).standard_normal(fem.rest.shape)
    torque = {}
    for per_point in (True, False):
        f, q = np.zeros_like(x), rest_quaternions(fem.n_rotations)
        p2_forces_range(x, fem.elems, fem.Bm, fem.vol, fem.mu, fem.lam, q, f, 0, fem.n_elems, per_point, 200, np.float64)
        torque[per_point] = np.abs(np.cross(x, f).sum(axis=0)).max() / np.abs(f).max()
    assert torque[True] < 1e-12 and torque[False] > 1e-3


@pytest.mark.parametrize("dim", [2, 3])
def test_patch_test_homogeneous_strain(dim):
    """An affine deformation: no force on any interior node, and the face x = L carries the
    stress of the strain times its area (the linear-elastic response, small strain)."""
    E, nu, eps = 4000.0, 0.3, 1e-4
    mu, lam = lame(E, nu)
    L, H, D = 1.0, 0.5, 0.25
    if dim == 3:
        pts, el = box_tets((3, 2, 2), (L, H, D))
    else:
        pts, el = box_tris((3, 2), (L, H))
    fem = build_fem(*quadratic_mesh(pts, el), 1.0, E, nu)
    stretch = np.r_[1 + eps, np.ones(dim - 1)]
    f = converged(fem, fem.rest * stretch)
    r = fem.rest
    interior = np.all((r > 1e-9) & (r < np.r_[L, H, D][:dim] - 1e-9), axis=1)
    assert interior.any()
    assert np.abs(f[interior]).max() < 1e-9 * np.abs(f).max()
    area = H * D if dim == 3 else H
    assert -f[r[:, 0] > L - 1e-9, 0].sum() / area == pytest.approx((lam + 2 * mu) * eps, rel=1e-3)


@pytest.mark.parametrize("dim", [2, 3])
def test_cantilever_quadratic_within_5_percent_with_one_and_two_layers(dim):
    """The issue's proof against Euler-Bernoulli, linear elements beside: a stubby beam
    (L / h = 6.7) whose converged answer lies between Euler-Bernoulli and Timoshenko."""
    beam = Beam()
    results = {}
    for layers in (1, 2):
        pts, el = structured_beam(beam, dim, layers)
        for order, mesh in ((1, (pts, el)), (2, quadratic_mesh(pts, el))):
            results[order, layers] = cantilever(beam, *mesh, periods=2.0)
    for layers in (1, 2):
        quad, lin = results[2, layers], results[1, layers]
        assert abs(quad["sag_error"]) < 0.05 and abs(quad["freq_error"]) < 0.05
        # linear elements lock: at least 30% too stiff here
        assert lin["sag_error"] < -0.3 and lin["freq_error"] > 0.2
    # the error against the shear-corrected (Timoshenko) deflection shrinks with refinement
    timo = [abs(results[2, n]["sag"] / results[2, n]["sag_timoshenko"] - 1) for n in (1, 2)]
    assert timo[1] < timo[0]


def test_free_quadratic_body_conserves_momentum():
    fem = p2_block(3)
    body = FreeBody(fem)
    rng = np.random.default_rng(3)
    body.v[:] = 0.3 * rng.standard_normal(body.v.shape)
    m = fem.mass[:, None]
    P0, L0 = (m * body.v).sum(0), np.cross(body.x, m * body.v).sum(0)
    body.run(2000)
    np.testing.assert_allclose((m * body.v).sum(0), P0, atol=1e-10)
    np.testing.assert_allclose(np.cross(body.x, m * body.v).sum(0), L0, atol=0.02 * np.linalg.norm(L0))


def test_stable_substep_of_quadratic_elements_is_near_the_limit():
    fem = p2_block(3)
    dt = stable_substep(fem, 1.0)
    for factor, ok in ((0.95, True), (1.3, False)):
        body = FreeBody(fem, safety=factor)
        body.dt = dt * factor
        body.v[:] = 1e-3 * np.random.default_rng(4).standard_normal(body.v.shape)
        body.run(3000)
        assert (np.abs(body.v).max() < 1.0) == ok


def test_boundary_subfaces_tile_the_corner_faces():
    from sdexp.sim.mesh.surface import boundary_faces, face_normals

    pts, el = box_tets((2, 1, 2), (1.0, 0.5, 0.5))
    p2, e2 = quadratic_mesh(pts, el)
    corner = boundary_faces(el)
    sub = boundary_subfaces(corner, e2)
    assert len(sub) == 4 * len(corner)
    # same oriented area: the four pieces of a flat face add up to it
    np.testing.assert_allclose(face_normals(p2, sub).sum(0), face_normals(pts, corner).sum(0), atol=1e-12)
    np.testing.assert_allclose(np.abs(face_normals(p2, sub)).sum(), np.abs(face_normals(pts, corner)).sum())
