"""The accuracy yardstick of bench_sim and validate_fem (sdexp.eval.convergence): the assembled
stiffness is the simulator's force linearised, the free-body static solve matches beam theory,
Richardson recovers a known limit."""
import numpy as np
import pytest

from sdexp import conf
from sdexp.eval.convergence import richardson, static_displacement, stiffness
from sdexp.sim.physics.fem import build_fem, elastic_forces
from sdexp.sim.physics.quadratic import quadratic_mesh
from sdexp.sim.mesh.structured import box_tets, box_tris


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("order", [1, 2])
def test_stiffness_is_the_kernels_force_linearised(dim, order):
    pts, el = box_tets((3, 2, 2), (1.0, 0.4, 0.6)) if dim == 3 else box_tris((4, 2), (1.0, 0.4))
    if order == 2:
        pts, el = quadratic_mesh(pts, el)
    fem = build_fem(pts, el, 1.0, 5000.0, 0.3)
    K = stiffness(fem)
    assert abs(K - K.T).max() < 1e-9 * abs(K).max()
    u = 1e-7 * np.random.default_rng(0).standard_normal(fem.rest.shape)
    f = elastic_forces(fem, fem.rest + u)
    np.testing.assert_allclose(K @ u.ravel(), -f.ravel(), atol=1e-4 * np.abs(f).max())


@pytest.mark.parametrize("order,layers,tol", [(2, 1, 0.002), (1, 8, 0.05)])
def test_free_beam_under_balanced_load_matches_beam_theory(order, layers, tol):
    """A free 8 m plane-strain strip, its weight held by upward forces at its ends: the
    midspan sags 5 w L^4 / (384 EI) relative to the ends, as a simply supported beam."""
    L, T, E, nu = 8.0, 0.1, 6000.0, 0.3
    pts, el = box_tris((int(round(L * layers / T)), layers), (L, T), (-L / 2, -T / 2))
    if order == 2:
        pts, el = quadratic_mesh(pts, el)
    fem = build_fem(pts, el, 1.0, E, nu)
    f = np.zeros_like(fem.rest)
    f[:, 1] -= fem.mass * 9.81
    for end in (-L / 2, L / 2):
        ids = np.flatnonzero(np.isclose(fem.rest[:, 0], end))
        f[ids, 1] += 9.81 / 2 / len(ids)
    u = static_displacement(fem, f)
    x = fem.rest[:, 0]
    sag = u[np.isclose(np.abs(x), L / 2), 1].mean() - u[np.isclose(x, 0.0), 1].mean()
    EI = E / (1 - nu ** 2) * T ** 3 / 12
    assert sag == pytest.approx(5 * (9.81 / L) * L ** 4 / (384 * EI), rel=tol)


def test_richardson_recovers_a_known_limit_and_flags_an_unconverged_series():
    h = np.array([0.4, 0.25, 0.1])
    value, order, unc = richardson(h, 3.0 - 2.0 * h ** 2)
    assert value == pytest.approx(3.0, rel=1e-9) and order == pytest.approx(2.0, rel=1e-6) and unc > 0
    value, order, unc = richardson(h, np.array([1.0, 1.2, 1.1]))   # not monotone: finest, its spread
    assert value == 1.1 and np.isnan(order) and unc == pytest.approx(0.1)


def test_the_load_is_the_same_on_every_mesh_of_a_drone(tmp_path):
    """The yardstick's thrusts come from the design's rotor normals: on the patch normals, the
    octopus's head rotor carried 1.09 N on one mesh and 0 N on the next (hover_thrust then
    traded it against a horizontal force the tilted patches made)."""
    from dataclasses import replace

    from sdexp.eval.convergence import load_thrusts
    from sdexp.sim.drone import build_drone

    cfg = conf.drone("octopus")
    thrusts = [load_thrusts(build_drone(replace(cfg, mesh=replace(cfg.mesh, edge_length=e, layers=1)),
                                        str(tmp_path), "quadratic"), 9.81, 2.0) for e in (0.5, 0.4)]
    np.testing.assert_allclose(thrusts[0], thrusts[1], rtol=0.01)
    assert thrusts[0][0] > 0.5   # the head rotor lifts its share


def test_the_references_carry_the_same_thrust_on_the_same_body_at_every_refinement(tmp_path):
    """The yardstick's reference meshes (outline: exact) hold the same body, within what a 1 mm
    chord takes off the petal tips, and the simulator carries each rotor's thrust as a traction
    over exactly its disc, on the drone's own mesh as on its references: the load's centroid
    stays on the anchor (equal shares per vertex, before, put it 1-7 cm off on these meshes)."""
    from dataclasses import replace

    from sdexp.eval.convergence import refined
    from sdexp.sim.drone import build_drone

    cfg = conf.drone("flower")
    drones = [build_drone(replace(cfg, mesh=refined(cfg.mesh, r, 3)), str(tmp_path), "quadratic") for r in (1.5, 2.0)]
    volumes = [d.fem.vol.sum() for d in drones]
    assert volumes[1] == pytest.approx(volumes[0], rel=2e-3)
    for d in drones + [build_drone(cfg, str(tmp_path), "quadratic")]:
        rot, x = d.rotors, d.fem.rest
        for r in range(rot.count):
            k = slice(rot.vert_ptr[r], rot.vert_ptr[r + 1])
            w = rot.weights[k]
            assert w.sum() == pytest.approx(1.0) and np.linalg.norm(w @ x[rot.verts[k]] - rot.anchors[r]) < 5e-3


def test_a_drone_of_ones_own_converges_to_its_file_and_a_volume_mesh_is_refused(tmp_path, monkeypatch):
    """A file drone's references are fTetWild meshes of its file r times finer with a tighter
    envelope (no layers, no design outline), through the cache like every reference. A tet-mesh
    file is used as given, so it has nothing to converge to: a clear refusal."""
    from dataclasses import replace

    import meshio

    from sdexp.errors import UserError
    from sdexp.eval.convergence import REFERENCE_ENVELOPE, converged_response, refined
    from tests.conftest import make_config
    from tests.sim.test_meshfile import box

    monkeypatch.chdir(tmp_path)
    v, f = box(2.0, 0.4, 1.0)
    meshio.write(tmp_path / "plate.stl", meshio.Mesh(v, [("triangle", f)]))
    rotors = "[[-0.8,0.2,-0.4],[0.8,0.2,-0.4],[0.8,0.2,0.4],[-0.8,0.2,0.4]]"
    drone = make_config("drone=custom", "drone.mesh.file=plate.stl", f"drone.rotors={rotors}",
                        "drone.num_sensors=2", "drone.mesh.edge_length=0.4").drone
    ref = refined(drone.mesh, 2.0, 3)
    assert (ref.edge_length, ref.envelope, ref.layers, ref.outline) == (0.2, REFERENCE_ENVELOPE, 0, drone.mesh.outline)
    out = converged_response(drone, str(tmp_path / "cache"), [1.0, 1.5, 2.0])
    assert len(out["h"]) == 3 and out["compliance_converged"] > 0 and np.isfinite(out["bend_converged"])
    assert converged_response(drone, str(tmp_path / "cache"), [1.0, 1.5, 2.0])["h"] == out["h"]   # read back
    tets = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    meshio.write(tmp_path / "plate.vtu", meshio.Mesh(v, [("tetra", tets)]))
    with pytest.raises(UserError, match="plate.vtu is a volume mesh"):
        converged_response(replace(drone, mesh=replace(drone.mesh, file="plate.vtu")), str(tmp_path / "cache"), [1.0])
