"""The six 3D drones of the paper's table: surfaces, anchors, sensor placement, tet meshes."""

import numpy as np
import pytest

from sdexp import conf
from sdexp.sim.mesh.placement import tree_imus
from sdexp.sim.mesh.shapes.shapes3d import SHAPES
from sdexp.sim.mesh.tetmesh import tet_mesh

NAMES = sorted(SHAPES)


def drone_cfg(name):
    return conf.read("drone", name)


def make(name, **override):
    cfg = drone_cfg(name)
    args = dict(size=list(cfg.size), thickness=cfg.get("thickness"), num_rotors=cfg.num_rotors,
                num_sensors=cfg.num_sensors, params=dict(cfg.get("params", {})))
    args.update(override)
    return SHAPES[cfg.shape](args["size"], args["thickness"], args["num_rotors"],
                             args["num_sensors"], args["params"])


@pytest.fixture(scope="module")
def shapes():
    return {name: make(name) for name in NAMES}


def surface_volume(vertices, faces):
    p0, p1, p2 = (vertices[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0


def boundary_faces(tets):
    a, b, c, d = tets.T
    faces = np.concatenate([np.c_[b, c, d], np.c_[a, d, c], np.c_[a, b, d], np.c_[a, c, b]])
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                                   return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def assert_closed_outward(vertices, faces):
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, counts = np.unique(directed, axis=0, return_counts=True)
    assert (counts == 1).all(), "a directed edge is used twice: inconsistent orientation"
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert (counts == 2).all(), "an edge is not shared by exactly two faces"
    assert surface_volume(vertices, faces) > 0


def closest_faces(point, vertices, faces):
    """Distance from point to every triangle (exact), shape (m,)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", point - a, n)
    q = point - h[:, None] * n
    inside = np.ones(len(faces), dtype=bool)
    for p0, p1 in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(p1 - p0, q - p0), n) >= 0
    edge = np.full(len(faces), np.inf)
    for p0, p1 in ((a, b), (b, c), (c, a)):
        d = p1 - p0
        s = np.clip(np.einsum("ij,ij->i", point - p0, d) / np.einsum("ij,ij->i", d, d), 0, 1)
        edge = np.minimum(edge, np.linalg.norm(point - (p0 + s[:, None] * d), axis=1))
    return np.where(inside, np.abs(h), edge), n


@pytest.mark.parametrize("name", NAMES)
def test_surface_is_closed_and_outward(shapes, name):
    s = shapes[name]
    assert s.dim == 3 and s.vertices.shape[1] == 3 and s.faces.shape[1] == 3
    assert_closed_outward(s.vertices, s.faces)


@pytest.mark.parametrize("name", NAMES)
def test_bounding_box_matches_the_table(shapes, name):
    v, size = shapes[name].vertices, np.array(drone_cfg(name).size)
    lo, hi = v.min(axis=0), v.max(axis=0)
    np.testing.assert_allclose(hi - lo, size, rtol=0.02)
    np.testing.assert_allclose((lo + hi)[[0, 2]], 0.0, atol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_counts_follow_the_config(shapes, name):
    s, cfg = shapes[name], drone_cfg(name)
    assert s.rotors.shape == s.rotor_normals.shape == (cfg.num_rotors, 3)
    assert s.imus.shape == s.imu_normals.shape == (cfg.num_sensors, 3)
    assert s.frame_imus.shape == s.frame_normals.shape
    if name == "donut":  # no centre IMU: the ring IMUs define the frame
        np.testing.assert_array_equal(s.frame_imus, s.imus)
    else:
        assert len(s.frame_imus) == 1
        np.testing.assert_allclose(s.frame_imus[0, [0, 2]], s.center[[0, 2]], atol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_anchors_sit_on_the_upper_surface(shapes, name):
    s = shapes[name]
    thickness = drone_cfg(name).get("thickness") or drone_cfg(name).size[1]
    for points, normals in ((s.rotors, s.rotor_normals), (s.imus, s.imu_normals),
                            (s.frame_imus, s.frame_normals)):
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
        assert (normals[:, 1] > 0).all()
        for p, n in zip(points, normals):
            dist, face_n = closest_faces(p, s.vertices, s.faces)
            near = dist < 0.1 * thickness  # curved drones: the facets' sag from the true bend
            assert near.any(), f"anchor {p} is {dist.min():.4f} m off the surface"
            assert (face_n[near] @ n).max() > 0.5, "the anchor is not on the upper side"


@pytest.mark.parametrize("name", NAMES)
def test_imus_follow_the_placement_rule(shapes, name):
    s = shapes[name]
    expected = tree_imus(s.center, s.rotors, len(s.imus))
    np.testing.assert_allclose(s.imus[:, [0, 2]], expected, atol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_tet_mesh_at_the_configured_resolution(shapes, name):
    """Positive tets filling the surface; a mesh of simulator size (500 to 3,500 quadratic tets aimed
    at); every rotor and IMU patch (upper-surface faces within the configured radius, as the
    drone builder picks them) binds at least 4 nodes. One mesh per test, so pytest-xdist
    spreads the meshing over its workers."""
    s, cfg = shapes[name], drone_cfg(name)
    points, tets = tet_mesh(s.vertices, s.faces, cfg.mesh.edge_length,
                            cfg.mesh.get("stop_energy", 10.0), cfg.mesh.get("coarsen", False))
    assert points.dtype == np.float64 and tets.dtype == np.int32
    assert points.flags.c_contiguous and tets.flags.c_contiguous
    assert np.array_equal(np.unique(tets), np.arange(len(points)))
    vol = np.linalg.det(points[tets[:, 1:]] - points[tets[:, :1]]) / 6.0
    assert (vol > 0).all()
    boundary = boundary_faces(tets)
    assert_closed_outward(points, boundary)
    np.testing.assert_allclose(surface_volume(points, boundary), vol.sum(), rtol=1e-9)
    np.testing.assert_allclose(vol.sum(), surface_volume(s.vertices, s.faces), rtol=0.03)
    assert 500 <= len(tets) <= 3500

    # the drone builder's binding on the default (quadratic) elements: mid-edge nodes count
    from sdexp.sim.drone import assemble_drone
    built = assemble_drone(conf.drone(name), s, points, tets, "quadratic")
    assert np.diff(built.rotors.vert_ptr).min() >= 4
    assert (built.imus.w > 0).sum(axis=1).min() >= 4


@pytest.mark.parametrize("name", NAMES)
def test_a_count_the_shape_cannot_make_raises(name):
    cfg = drone_cfg(name)
    with pytest.raises(ValueError, match=rf"{cfg.shape}.*num_rotors = {cfg.num_rotors + 1}"):
        make(name, num_rotors=cfg.num_rotors + 1)


@pytest.mark.parametrize("name", NAMES)
def test_an_unknown_param_raises_and_lists_the_known(name):
    cfg = drone_cfg(name)
    known = sorted(cfg.get("params", {}))
    with pytest.raises(ValueError, match="no_such_param") as err:
        make(name, params={"no_such_param": 1.0})
    assert all(k in str(err.value) for k in known)


def test_donut_needs_its_four_ring_imus():
    with pytest.raises(ValueError, match="donut.*num_sensors = 3"):
        make("donut", num_sensors=3)


def test_fewer_sensors_than_arms_still_follow_the_rule():
    s = make("octopus", num_sensors=4)
    np.testing.assert_allclose(s.imus[:, [0, 2]], tree_imus(s.center, s.rotors, 4), atol=1e-12)


def box_surface(lx=1.0, ly=0.2, lz=0.6):
    v = np.array([[x, y, z] for x in (0, lx) for y in (0, ly) for z in (0, lz)], dtype=float)
    # two outward triangles per side of the box (vertex index = 4x + 2y + z)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int32)
    return v, faces


def test_box_surface_is_outward():
    assert_closed_outward(*box_surface())


def test_tet_mesh_is_deterministic_and_leaves_cwd_clean(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    v, f = box_surface()
    p1, t1 = tet_mesh(v, f, 0.15)
    p2, t2 = tet_mesh(v, f, 0.15)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(t1, t2)
    vol = np.linalg.det(p1[t1[:, 1:]] - p1[t1[:, :1]]) / 6.0
    assert (vol > 0).all()
    np.testing.assert_allclose(vol.sum(), 0.12, rtol=1e-3)
    assert list(tmp_path.iterdir()) == []


def test_tet_mesh_rejects_a_bad_edge_length():
    with pytest.raises(ValueError, match="edge_length"):
        tet_mesh(*box_surface(), 0.0)


@pytest.mark.parametrize("name", ["star", "flower"])
def test_thin_lobes_keep_the_bounding_box(name):
    cfg = drone_cfg(name)
    plain = {k: v for k, v in cfg.params.items() if k not in ("lobe_thickness", "thin_from")}   # an even plate
    s = make(name, params={**plain, "lobe_thickness": 0.4})
    assert_closed_outward(s.vertices, s.faces)
    np.testing.assert_allclose(np.ptp(s.vertices, axis=0), np.array(cfg.size), rtol=0.02)
    # the wall is as thick as the y size over the hub and 0.4 of it over the lobes
    rho = np.hypot(s.vertices[:, 0], s.vertices[:, 2])
    t = float(cfg.size[1])
    centre = rho < 0.2
    assert np.abs(s.vertices[centre, 1]).max() == pytest.approx(t / 2, rel=1e-6)
    tips = rho > 0.99 * rho.max()
    np.testing.assert_allclose(np.abs(s.vertices[tips, 1]), 0.4 * t / 2, rtol=0.03)
    # an anchor sits on the upper surface at its local thickness: outer rotors lower than the centre one
    assert s.rotors[1:, 1].max() < s.rotors[0, 1] - 0.1 * t
    for p in s.rotors:
        dist, _ = closest_faces(p, s.vertices, s.faces)
        assert dist.min() < 1e-3 * t   # the caps' facets against the taper, linear in rho
    even = make(name, params={**plain, "lobe_thickness": 1.0})
    np.testing.assert_array_equal(even.vertices, make(name, params=plain).vertices)   # 1: the even plate, unchanged
    with pytest.raises(ValueError, match="lobe_thickness"):
        make(name, params={**plain, "lobe_thickness": 1.5})
    # thin_from < 1: only a central pod keeps the full thickness, the hub's rim is thin too
    hub = float(cfg.params[{"star": "body_radius", "flower": "disc_radius"}[name]])
    pod = make(name, params={**plain, "lobe_thickness": 0.4, "thin_from": 0.25})
    np.testing.assert_allclose(np.ptp(pod.vertices, axis=0), np.array(cfg.size), rtol=0.02)
    r = np.hypot(pod.vertices[:, 0], pod.vertices[:, 2])
    assert np.abs(pod.vertices[r < 0.2 * hub, 1]).max() == pytest.approx(t / 2, rel=1e-6)
    rim = (r > 0.25 * hub + 0.25 * (rho.max() - hub) + 1e-3) & (r < hub)
    assert rim.any()
    np.testing.assert_allclose(np.abs(pod.vertices[rim, 1]), 0.4 * t / 2, rtol=1e-6)
    with pytest.raises(ValueError, match="thin_from"):
        make(name, params={**plain, "thin_from": 1.5})
