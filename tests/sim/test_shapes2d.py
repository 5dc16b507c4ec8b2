"""The 2D drones (supplement B) and their meshes, each as configured in conf/drone/."""
from __future__ import annotations


import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from sdexp import conf
from sdexp.config import DroneConfig
from sdexp.sim.mesh.placement import tree_imus
from sdexp.sim.mesh.shapes.shapes2d import ROOT_RADIUS, SHAPES
from sdexp.sim.mesh.trimesh import tri_mesh

# Supplement B, table "2D models": size (x, y), rotors, sensors; the rod read as horizontal.
TABLE = {
    "engine": ((1.90, 2.16), 6, 6),
    "bunny": ((1.12, 1.75), 3, 3),
    "diamond": ((1.47, 1.42), 4, 8),
    "elephant": ((2.46, 1.69), 2, 3),
    "rainbow": ((2.08, 1.30), 2, 4),
    "rod": ((8.0, 0.1), 5, 8),
}


def _config(name):
    return OmegaConf.merge(OmegaConf.structured(DroneConfig), conf.read("drone", name))


def _make(cfg):
    return SHAPES[cfg.shape](cfg.size, cfg.thickness, cfg.num_rotors, cfg.num_sensors, cfg.params)


@pytest.fixture(scope="module", params=sorted(TABLE))
def drone(request):
    cfg = _config(request.param)
    shape = _make(cfg)
    points, tris = tri_mesh(shape.vertices, shape.faces, shape.holes, cfg.mesh.edge_length)
    return request.param, cfg, shape, points, tris


def _rings(faces):
    following = dict(faces.tolist())
    rings, seen = [], set()
    for start in following:
        if start in seen:
            continue
        ring = [start]
        while following[ring[-1]] != start:
            ring.append(following[ring[-1]])
        seen.update(ring)
        rings.append(ring)
    return rings


def _signed_area(pts):
    x, y = pts[:, 0], pts[:, 1]
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def _boundary_distance(points, shape):
    a, b = shape.vertices[shape.faces[:, 0]], shape.vertices[shape.faces[:, 1]]
    d = b - a
    rel = points[:, None, :] - a[None]
    t = np.clip((rel * d).sum(-1) / (d * d).sum(-1), 0, 1)
    return np.linalg.norm(rel - t[..., None] * d, axis=-1).min(axis=1)


def _tri_areas(points, tris):
    a, b, c = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    ab, ac = b - a, c - a
    return 0.5 * (ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0])


def test_config_matches_table(drone):
    name, cfg, *_ = drone
    size, rotors, sensors = TABLE[name]
    assert (cfg.dim, cfg.shape, cfg.name) == (2, name, name)
    assert list(cfg.size) == pytest.approx(size)
    assert (cfg.num_rotors, cfg.num_sensors) == (rotors, sensors)
    assert (cfg.mass, cfg.youngs_modulus, cfg.max_thrust) == (1.0, 6e3, 10.0)


def test_closed_oriented_boundary(drone):
    _, _, shape, _, _ = drone
    assert shape.dim == 2 and shape.vertices.shape[1] == 2 and shape.faces.shape[1] == 2
    assert np.all(np.bincount(shape.faces.ravel(), minlength=len(shape.vertices)) == 2)
    areas = sorted((_signed_area(shape.vertices[r]) for r in _rings(shape.faces)), key=abs)
    assert areas[-1] > 0, "outer boundary must run counter-clockwise"
    assert all(a < 0 for a in areas[:-1]), "holes must run clockwise"
    assert shape.holes.shape == (len(areas) - 1, 2)


def test_bounding_box(drone):
    name, _, shape, _, _ = drone
    lo, hi = shape.vertices.min(axis=0), shape.vertices.max(axis=0)
    np.testing.assert_allclose(hi - lo, TABLE[name][0], rtol=0.02)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-9)


def test_counts(drone):
    name, _, shape, _, _ = drone
    _, rotors, sensors = TABLE[name]
    assert shape.rotors.shape == shape.rotor_normals.shape == (rotors, 2)
    assert shape.imus.shape == shape.imu_normals.shape == (sensors, 2)
    assert shape.frame_imus.shape == shape.frame_normals.shape == (1, 2)
    assert shape.center.shape == (2,)


def test_anchors_on_upper_boundary(drone):
    _, _, shape, _, _ = drone
    for anchors, normals in ((shape.rotors, shape.rotor_normals), (shape.imus, shape.imu_normals),
                             (shape.frame_imus, shape.frame_normals)):
        assert np.all(_boundary_distance(anchors, shape) < 1e-9)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
        assert np.all(normals[:, 1] > 0)
    # Positive thrust lifts: every rotor pushes mostly upwards.
    assert np.all(shape.rotor_normals[:, 1] > 0.5)


def test_imus_follow_placement_rule(drone):
    _, cfg, shape, _, _ = drone
    expected = tree_imus(shape.center, shape.rotors, cfg.num_sensors,
                         cfg.params.get("root_radius", ROOT_RADIUS))
    np.testing.assert_allclose(shape.imus[:, 0], expected[:, 0], atol=1e-12)
    np.testing.assert_allclose(shape.frame_imus[0, 0], shape.center[0], atol=1e-12)


def test_mesh(drone):
    _, _, shape, points, tris = drone
    assert points.dtype == np.float64 and tris.dtype == np.int32
    assert 50 <= len(tris) <= 1500
    areas = _tri_areas(points, tris)
    assert np.all(areas > 0)
    polygon = sum(_signed_area(shape.vertices[r]) for r in _rings(shape.faces))
    assert areas.sum() == pytest.approx(polygon, rel=0.01)
    assert np.array_equal(np.unique(tris), np.arange(len(points)))
    # One connected body: triangles sharing an edge are neighbours.
    edges = np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, owner = np.unique(edges, axis=0, return_inverse=True)
    owner = owner.ravel()
    tri_of = np.repeat(np.arange(len(tris)), 3)
    order = np.argsort(owner, kind="stable")
    same = owner[order][1:] == owner[order][:-1]
    i, j = tri_of[order][:-1][same], tri_of[order][1:][same]
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(len(tris), len(tris)))
    assert connected_components(graph, directed=False)[0] == 1


def test_patches_catch_three_boundary_vertices(drone):
    """Every rotor and IMU of the default (quadratic) drone binds at least three boundary
    nodes: a segment's mid-edge node counts, as it carries thrust and reads the IMU frame."""
    from sdexp.sim.drone import assemble_drone
    _, cfg, shape, points, tris = drone
    built = assemble_drone(cfg, shape, points, tris, "quadratic")
    assert np.diff(built.rotors.vert_ptr).min() >= 3
    assert (built.imus.w > 0).sum(axis=1).min() >= 3


def test_deterministic(drone):
    _, cfg, shape, points, tris = drone
    again = _make(cfg)
    for field in ("vertices", "faces", "rotors", "imus", "frame_imus"):
        assert np.array_equal(getattr(shape, field), getattr(again, field))
    p2, t2 = tri_mesh(again.vertices, again.faces, again.holes, cfg.mesh.edge_length)
    assert np.array_equal(points, p2) and np.array_equal(tris, t2)


@pytest.mark.parametrize("name", sorted(TABLE))
def test_other_counts(name):
    size, _, _ = TABLE[name]
    for rotors in {"engine": (3, 9), "bunny": (1, 2)}.get(name, (2, 3)):
        shape = SHAPES[name](size, None, rotors, 5, {})
        assert len(shape.rotors) == rotors and len(shape.imus) == 5
        assert np.all(shape.rotor_normals[:, 1] > 0)


@pytest.mark.parametrize("name,rotors,sensors", [
    ("engine", 4, 6),      # 4 rotors cannot share 3 cylinder heads
    ("bunny", 4, 3),       # 3 rotor sites only
    ("rod", 1, 2),         # a lone rotor at the centre leaves the sensor tree without edges
    ("diamond", 0, 8),
    ("rainbow", 2, -1),
])
def test_bad_count_raises(name, rotors, sensors):
    with pytest.raises(ValueError, match=name):
        SHAPES[name](TABLE[name][0], None, rotors, sensors, {})


def test_unknown_param_raises():
    with pytest.raises(ValueError, match="known params.*rotor_inset"):
        SHAPES["rod"]((8.0, 0.1), None, 5, 8, {"rotor_spacing": 2.0})


def test_tri_mesh_square_with_hole():
    outer = [(0, 0), (0, 1), (2, 1), (2, 0)]  # clockwise on purpose: output must still be CCW
    hole = [(0.5, 0.25), (1.5, 0.25), (1.5, 0.75), (0.5, 0.75)]
    vertices = np.array(outer + hole, dtype=float)
    segments = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4)]
    points, tris = tri_mesh(vertices, segments, [(1.0, 0.5)], 0.1)
    areas = _tri_areas(points, tris)
    assert np.all(areas > 0) and areas.sum() == pytest.approx(1.5)
    assert np.array_equal(np.unique(tris), np.arange(len(points)))
    assert np.all(np.sqrt(4 / np.sqrt(3) * areas) < 0.1 * 1.01)  # no triangle above the area bound
