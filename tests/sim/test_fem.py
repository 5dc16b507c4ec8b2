"""The FEM core against physics: invariances, conservation laws, analytic beams and the
rigid-body limit, 2D against 3D in plane strain."""
import numba
import numpy as np
import pytest

from sdexp.eval.validate_fem import Beam, FreeBody, cantilever, stiff_plate_under_thrust, structured_beam
from sdexp.sim.physics.integrator import Body
from sdexp.sim.physics.fem import build_fem, elastic_forces, lame, rest_quaternions, stable_substep
from sdexp.sensing.rotations import matrix_from_euler
from sdexp.sim.mesh.structured import box_tets, box_tris


@pytest.fixture(scope="module")
def block():
    pts, tets = box_tets((4, 2, 3), (1.0, 0.4, 0.6), (-0.5, -0.2, -0.3))
    return build_fem(pts, tets, 1.0, 5000.0, 0.3)


def converged_forces(fem, x):
    q = rest_quaternions(fem.n_elems)
    for _ in range(30):  # warm-started polar iterations: converge them fully
        f = elastic_forces(fem, x, q)
    return f


def test_rigid_motion_produces_no_elastic_force(block):
    R = matrix_from_euler(np.array([0.7, -1.2, 0.4]))
    x = block.rest @ R.T + np.array([3.0, -2.0, 5.0])
    f = converged_forces(block, x)
    scale = block.mu * np.ptp(block.rest)  # a typical force for unit strain
    assert np.abs(f).max() < 1e-8 * scale


def test_rotated_deformation_rotates_forces(block):
    """Frame indifference: deform, then rotate rigidly: the forces rotate with the body."""
    rng = np.random.default_rng(1)
    x = block.rest + 0.02 * rng.standard_normal(block.rest.shape)
    R = matrix_from_euler(np.array([0.3, 2.0, -0.5]))
    f0 = converged_forces(block, x)
    f1 = converged_forces(block, x @ R.T)
    np.testing.assert_allclose(f1, f0 @ R.T, atol=1e-9 * np.abs(f0).max())


def test_internal_forces_sum_to_zero_with_zero_torque(block):
    rng = np.random.default_rng(2)
    x = block.rest + 0.05 * rng.standard_normal(block.rest.shape)
    f = converged_forces(block, x)
    assert np.abs(f.sum(axis=0)).max() < 1e-9 * np.abs(f).max()
    assert np.abs(np.cross(x, f).sum(axis=0)).max() < 1e-8 * np.abs(f).max()


def test_free_body_conserves_momentum(block):
    """No gravity, no damping: linear momentum exact; angular momentum up to the error of the
    warm-started polar rotation (two iterations a substep, so R^T F is nearly symmetric)."""
    body = FreeBody(block)
    rng = np.random.default_rng(3)
    body.v[:] = 0.3 * rng.standard_normal(body.v.shape)
    m = block.mass[:, None]
    P0 = (m * body.v).sum(0)
    L0 = np.cross(body.x, m * body.v).sum(0)
    body.run(2000)
    np.testing.assert_allclose((m * body.v).sum(0), P0, atol=1e-10)
    np.testing.assert_allclose(np.cross(body.x, m * body.v).sum(0), L0, atol=0.02 * np.linalg.norm(L0))


def test_stable_substep_is_near_the_limit(block):
    """Power-iteration estimate: stable at the estimate, unstable well above it."""
    dt = stable_substep(block, 1.0)
    for factor, ok in ((0.95, True), (1.3, False)):
        body = FreeBody(block, safety=factor)
        body.dt = dt * factor
        body.v[:] = 1e-3 * np.random.default_rng(4).standard_normal(body.v.shape)
        body.run(3000)
        assert (np.abs(body.v).max() < 1.0) == ok


def test_stable_substep_is_found_once_per_body_content(block, monkeypatch):
    """Every simulator of a body (a fleet job builds dozens) shares one power iteration: a copy
    of the model reads it, a changed mass or safety does not."""
    from copy import deepcopy
    from sdexp.sim.physics import fem
    dt = stable_substep(block, 1.0)
    calls = []
    real = fem._power_iteration
    monkeypatch.setattr(fem, "_power_iteration", lambda *a: calls.append(1) or real(*a))
    assert stable_substep(deepcopy(block), 1.0) == dt and not calls
    heavier = stable_substep(block, 1.0, mass=2.0 * block.mass)
    assert heavier == pytest.approx(np.sqrt(2.0) * dt, rel=1e-6) and len(calls) == 1
    assert stable_substep(block, 0.5) == real(block, block.mass, 0.5, 60, 0) and len(calls) == 2


def test_homogeneous_plane_strain_matches_3d_and_theory():
    """Stretch a block by 1% in x with no strain in z: the 3D and the 2D plane-strain models
    both give sigma_xx = (lambda + 2 mu) eps on the x = L face."""
    E, nu, eps = 4000.0, 0.3, 0.01
    mu, lam = lame(E, nu)
    L, H, D = 1.0, 0.5, 0.25
    p3, t3 = box_tets((4, 2, 1), (L, H, D))
    f3 = elastic_forces(build_fem(p3, t3, 1.0, E, nu), p3 * [1 + eps, 1, 1])
    p2, t2 = box_tris((4, 2), (L, H))
    f2 = elastic_forces(build_fem(p2, t2, 1.0, E, nu), p2 * [1 + eps, 1])
    s3 = -f3[p3[:, 0] > L - 1e-9, 0].sum() / (H * D)
    s2 = -f2[p2[:, 0] > L - 1e-9, 0].sum() / H
    expected = (lam + 2 * mu) * eps
    assert s3 == pytest.approx(expected, rel=1e-3)
    assert s2 == pytest.approx(expected, rel=1e-3)


def test_cantilever_converges_to_euler_bernoulli_in_2d():
    beam = Beam()
    errors = []
    for layers in (2, 4, 8):
        res = cantilever(beam, *structured_beam(beam, 2, layers))
        errors.append((abs(res["sag_error"]), abs(res["freq_error"])))
    sag, freq = np.array(errors).T
    assert np.all(np.diff(sag) < 0) and np.all(np.diff(freq) < 0)
    # 8 layers: within shear deformation (Timoshenko, ~2.6% here) of Euler-Bernoulli
    assert sag[-1] < 0.04 and freq[-1] < 0.03


def test_cantilever_refines_in_3d():
    beam = Beam()
    res = [cantilever(beam, *structured_beam(beam, 3, n), periods=2.0) for n in (1, 2)]
    assert abs(res[1]["sag_error"]) < abs(res[0]["sag_error"])
    assert abs(res[1]["freq_error"]) < abs(res[0]["freq_error"])
    # linear tets lock in bending: too stiff, never too soft
    assert all(r["sag_error"] < 0 and r["freq_error"] > 0 for r in res)


def test_stiff_limit_follows_rigid_body_motion():
    res = stiff_plate_under_thrust()
    assert res["rise"] == pytest.approx(res["rise_rigid"], rel=0.01)
    assert res["drift"] < 1e-9
    assert res["max_deformation"] < 0.01


def test_compiled_kernel_matches_the_numba_reference(block):
    from sdexp.sim.physics.fem import kernels
    from sdexp.sim.physics.reference import corotated_forces_3d

    kernel = kernels().forces_3d
    assert kernel is not corotated_forces_3d.ctypes, "the C kernel did not build"
    rng = np.random.default_rng(5)
    x = block.rest @ matrix_from_euler(np.array([0.4, 1.0, -0.3])).T + 0.05 * rng.standard_normal(block.rest.shape)
    q1, q2 = rest_quaternions(block.n_elems), rest_quaternions(block.n_elems)
    for _ in range(3):  # warm starts evolve the same way
        f_c = elastic_forces(block, x, q1, kernel)
        f_nb = elastic_forces(block, x, q2, corotated_forces_3d.ctypes)
    np.testing.assert_allclose(f_c, f_nb, atol=1e-10 * np.abs(f_nb).max())
    np.testing.assert_allclose(q1, q2, atol=1e-12)


def rotor_block(dim: int, order: int):
    """(fem, rotors) of the 1 x 0.4 (x 0.6) m block the step tests spin: linear or quadratic
    elements, one rotor pushing up off-centre."""
    from sdexp.sim.drone import build_rotors
    from sdexp.sim.mesh.surface import boundary_faces
    from sdexp.sim.physics.quadratic import boundary_subfaces, quadratic_mesh

    if dim == 3:
        pts, el = box_tets((4, 2, 3), (1.0, 0.4, 0.6), (-0.5, -0.2, -0.3))
    else:
        pts, el = box_tris((8, 3), (1.0, 0.4), (-0.5, -0.2))
    faces = boundary_faces(el)
    if order == 2:
        pts, el = quadratic_mesh(pts, el)
        faces = boundary_subfaces(faces, el)
    fem = build_fem(pts, el, 1.0, 5000.0, 0.3)
    up = np.eye(dim)[1]
    rotors = build_rotors(fem.rest, el, faces, [0.2 * up + 0.3 * np.eye(dim)[0]], [up], 0.3, "test")
    return fem, rotors


def spun_block(dim: int, order: int):
    """rotor_block, spun: (fem, rotors, v0, added, pinned) with a rigid spin plus noise as the
    start velocity, added inertia on every fifth vertex, three pinned vertices at one end."""
    fem, rotors = rotor_block(dim, order)
    rng = np.random.default_rng(11)
    v0 = _rigid_field(fem.rest, rng, dim) + 0.2 * rng.standard_normal(fem.rest.shape)
    added = np.where(np.arange(len(fem.rest)) % 5 == 0, 0.2 * fem.mass, 0.0)
    pinned = np.flatnonzero(fem.rest[:, 0] < -0.45)[:3]
    return fem, rotors, v0, added, pinned


@pytest.mark.parametrize("precision,tol,tol_speed", [("float64", 1e-10, 1e-9), ("float32", 2e-4, 1e-3)])
@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_step_matches_the_numba_reference(dim, threads, order, precision, tol, tol_speed):
    """kernels.c's advance (one OpenMP region per control step) against reference.advance:
    a block spun and thrown onto the ground and into a box, with a rotor, gravity, both
    dampings and added inertia on a few nodes (gravity on the physical mass), so every branch
    of the step runs; linear and quadratic elements; forces in float64 and in float32. In
    float32 the two kernels round differently (fused multiply-adds, summation order): their
    forces agree to 5e-7 (test_float32_kernels_agree), which 600 substeps with contacts and
    friction carry to 6e-5 of the block's size (the 2D quadratic block; 3D: 1e-6)."""
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    fem, rotors = rotor_block(dim, order)
    lo, hi = np.full(dim, -0.1), np.full(dim, 2.0)
    lo[0] = 0.55  # a wall the block slides into
    rng = np.random.default_rng(7)
    v0 = _rigid_field(fem.rest, rng, dim) + 0.2 * rng.standard_normal(fem.rest.shape) + np.r_[1.5, -1.0, 0.0][:dim]
    added = np.where(np.arange(len(fem.rest)) % 7 == 0, 0.3 * fem.mass, 0.0)
    bodies = [Body(fem, threads, rotors, ground=-0.35, boxes_min=lo, boxes_max=hi, friction=0.5, compiled=c,
                   precision=precision, added_mass=added) for c in (True, False)]
    assert bodies[0]._step is not None, "the C kernels did not build"
    c, ref = bodies
    for body in bodies:
        body.v[:] = v0
    touched = np.zeros(2, bool)
    for _ in range(30):
        (worst_c, vmax_c), (worst_nb, vmax_nb) = (body.run(20 * order, 2e-4 / order, [3.0], 0.5, 9.81, 20.0) for body in bodies)
        assert worst_c == worst_nb and vmax_c == pytest.approx(vmax_nb, rel=tol_speed)
        on_wall = np.isclose(ref.x[:, 0], 0.55, rtol=0, atol=1e-12) & (ref.x[:, 1] > lo[1])
        touched |= [np.isclose(ref.x[:, 1].min(), -0.35), on_wall.any()]
    assert touched.all(), "the block should touch the ground and the wall"
    scale = np.abs(ref.x).max()
    np.testing.assert_allclose(c.x, ref.x, atol=tol * scale)
    np.testing.assert_allclose(c.v, ref.v, atol=10 * tol * np.abs(ref.v).max())
    np.testing.assert_allclose(c.quaternions(), ref.quaternions(), atol=tol if precision == "float64" else 1e-4)
    np.testing.assert_allclose(c.dirs, ref.dirs, atol=tol)


@pytest.mark.parametrize("deform_damping", [0.0, 20.0])
@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_step_without_contacts_matches_the_numba_reference(dim, threads, order, deform_damping):
    """The step's SIMD loops over vertices (kernels.c: kick's tiles, drift without contacts, which
    the test above, with ground and a box, does not reach): a spun block with pinned vertices,
    a rotor, gravity, added inertia, with and without deformation damping, against the numba
    reference to 1e-10; and two compiled bodies stepped alike are bitwise equal."""
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    fem, rotors, v0, added, pinned = spun_block(dim, order)
    bodies = [Body(fem, threads, rotors, pinned=pinned, compiled=c, added_mass=added) for c in (True, True, False)]
    assert bodies[0]._step is not None, "the C kernels did not build"
    for body in bodies:
        body.v[:] = v0
        body.v[pinned] = 0.0
    for _ in range(20):
        out = [body.run(10 * order, 2e-4 / order, [3.0], 0.5, 9.81, deform_damping) for body in bodies]
        assert out[0] == out[1] and out[0][0] == out[2][0]
        assert out[0][1] == pytest.approx(out[2][1], rel=1e-9)
    c, twin, ref = bodies
    for a in ("x", "v", "q"):
        np.testing.assert_array_equal(getattr(c, a), getattr(twin, a))
    np.testing.assert_array_equal(c.x[pinned], fem.rest[pinned])
    np.testing.assert_allclose(c.x, ref.x, atol=1e-10 * np.abs(ref.x).max())
    np.testing.assert_allclose(c.v, ref.v, atol=1e-9 * np.abs(ref.v).max())


def test_without_a_compiler_the_numba_kernels_run(block, tmp_path, monkeypatch):
    """No working C compiler: a warning, no half-built library left, and bodies still step."""
    from sdexp.sim.physics import native

    monkeypatch.setenv("SDEXP_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")
    native.library.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="numba"):
            body = FreeBody(block)
        assert body._step is None and not list(tmp_path.iterdir())
        body.run(10)
        assert np.isfinite(body.x).all()
    finally:
        native.library.cache_clear()


def _rigid_field(x, rng, dim):
    w = rng.standard_normal(3)
    if dim == 2:
        w[:2] = 0.0
    x3 = np.pad(x, ((0, 0), (0, 3 - dim)))
    return (rng.standard_normal(3) + np.cross(w, x3 - x3.mean(0)))[:, :dim]


def damp_deformation(x, v, mass, minv, keep):
    """The step's deformation damping alone (reference.kick's sums, rigid_motion, drift's damping),
    through the numba reference with a zero time step: nothing else moves."""
    from sdexp.sim.physics.reference import S_LEN, drift, kick, rigid_motion

    zeros, sums, ref = np.zeros_like(x), np.zeros(S_LEN), np.pad(x[0], (0, 3 - x.shape[1]))
    kick(x, v, zeros[None], minv, mass, zeros, zeros, 0.0, 1.0, 0.0, np.ones(len(x)), ref, True, sums)
    c, p, w = rigid_motion(sums, x.shape[1])
    none = np.zeros((0, x.shape[1]))
    drift(x, v, minv, 0.0, True, keep, ref, c, p, w, -np.inf, none, none, 0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_deformation_damping_keeps_momenta_and_rigid_motion(dim):
    """The frame-indifferent damping takes ``keep`` off the velocity relative to the rigid
    motion: a rigid velocity field is untouched, linear and angular momentum are unchanged."""
    rng = np.random.default_rng(5)
    n = 40
    x = rng.standard_normal((n, dim)); mass = rng.uniform(0.5, 2.0, n)
    rigid = _rigid_field(x, rng, dim)
    v = rigid.copy()
    damp_deformation(x, v, mass, 1 / mass, 0.3)
    np.testing.assert_allclose(v, rigid, atol=1e-12)
    v = rigid + rng.standard_normal((n, dim))
    v0 = v.copy()
    damp_deformation(x, v, mass, 1 / mass, 0.3)
    m = mass[:, None]
    pad = lambda a: np.pad(a, ((0, 0), (0, 3 - dim)))
    np.testing.assert_allclose((m * v).sum(0), (m * v0).sum(0), atol=1e-12)
    np.testing.assert_allclose(np.cross(pad(x), pad(m * v)).sum(0), np.cross(pad(x), pad(m * v0)).sum(0), atol=1e-12)
    # the part relative to the rigid motion shrank by exactly ``keep``: a second pass removes
    # 0.7 of what is left, i.e. 0.3 times what the first removed
    v1 = v.copy()
    damp_deformation(x, v1, mass, 1 / mass, 0.3)
    assert np.linalg.norm(v1 - v) == pytest.approx(0.3 * np.linalg.norm(v - v0), rel=1e-9)


def test_deformation_damping_stops_vibration_not_flight(block):
    """A spinning, drifting, vibrating block: deformation damping kills the vibration and keeps
    the momenta; mass-proportional damping of the absolute velocity slows the flight too."""
    rng = np.random.default_rng(6)
    m = block.mass[:, None]
    start = _rigid_field(block.rest, rng, 3) + 0.3 * rng.standard_normal(block.rest.shape)
    moments = lambda b: ((m * b.v).sum(0), np.cross(b.x, m * b.v).sum(0))
    results = {}
    for name, kw in (("deformation", {"deform_damping": 20.0}), ("absolute", {"damping": 20.0})):
        body = FreeBody(block)
        body.v[:] = start
        P0, L0 = moments(body)
        Body.run(body, 2400, body.dt, None, **kw)   # about 1 s
        P, L = moments(body)
        results[name] = (np.linalg.norm(P - P0) / np.linalg.norm(P0), np.linalg.norm(L - L0) / np.linalg.norm(L0))
        # the strain left: the body is back to a rigid shape up to its elastic stretch
        F = body.x - body.x.mean(0)
        if name == "deformation":
            w = np.linalg.solve(np.einsum("i,ij,ik->jk", block.mass, F, F).trace() * np.eye(3)
                                - np.einsum("i,ij,ik->jk", block.mass, F, F), L)
            rigid = P / block.mass.sum() + np.cross(w, F)
            assert np.linalg.norm(body.v - rigid) < 0.02 * np.linalg.norm(start - start.mean(0))
    # angular momentum: the polar iteration's drift, as in test_free_body_conserves_momentum
    assert results["deformation"][0] < 1e-9 and results["deformation"][1] < 0.05
    assert results["absolute"][0] > 0.9 and results["absolute"][1] > 0.9


def test_a_damaged_compiled_kernel_is_rebuilt_not_loaded(tmp_path, monkeypatch):
    """A truncated library would crash the process when loaded (bus error): the digest recorded
    at build time catches it first and the library is built again."""
    from sdexp.sim.physics import native

    monkeypatch.setenv("SDEXP_CACHE", str(tmp_path))
    so = native._library_path(tmp_path)
    native._build(so)                                   # built, not loaded: this process maps no copy
    assert native._intact(so)
    so.write_bytes(so.read_bytes()[:1000])              # truncated, as by a full disk
    assert not native._intact(so)
    native.library.cache_clear()
    try:
        assert native.library() is not None and native._intact(so)
    finally:
        native.library.cache_clear()
