"""A drone of one's own from a mesh file: reading (formats, units, orientation), the checks on a
body that is not closed, snapping rotors onto the surface and the IMU placement on it."""
from types import SimpleNamespace

import meshio
import numpy as np
import pytest
import triangle

from sdexp.errors import UserError
from sdexp.sim.mesh.meshfile import read_body
from sdexp.sim.mesh.shapes.from_file import make_file_shape
from sdexp.sim.mesh.snap import closest_points, snap
from sdexp.sim.mesh.surface import enclosed_centroid, enclosed_volume
from sdexp.sim.mesh.tetmesh import clean_tets

TRIPOD = [[0.0, 0.1, 0.0], [0.0, 0.1, 1.35], [-0.9397, 0.1, -0.342], [0.942, 0.1, -0.6596]]


def box(lx=2.0, ly=0.2, lz=1.0):
    """A closed outward box surface centred at the origin (8 corners, 12 triangles)."""
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * [lx / 2, ly / 2, lz / 2]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return v, f


def extruded(loops, holes=(), thickness=0.2):
    """The closed surface of planar (x, z) loops (outline CCW, holes CW) extruded along y."""
    pts = np.vstack(loops)
    start = np.cumsum([0] + [len(r) for r in loops])
    segs = np.vstack([np.c_[np.arange(s, e), np.r_[np.arange(s + 1, e), s]] for s, e in zip(start[:-1], start[1:])])
    pslg = {"vertices": pts, "segments": segs, **({"holes": np.array(holes)} if holes else {})}
    t = triangle.triangulate(pslg, "p")
    planar, caps = t["vertices"], t["triangles"]
    m = len(planar)
    v = np.r_[np.c_[planar[:, 0], np.full(m, -thickness / 2), planar[:, 1]],
              np.c_[planar[:, 0], np.full(m, thickness / 2), planar[:, 1]]]
    a, b = segs.T
    walls = np.r_[np.c_[a, b + m, b], np.c_[a, a + m, b + m]]
    return v, np.r_[caps, caps[:, [0, 2, 1]] + m, walls]


def circle(r, n=48, cw=False):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False) * (-1 if cw else 1)
    return r * np.c_[np.cos(t), np.sin(t)]


def write(path, points, cells, **kw):
    meshio.write(path, meshio.Mesh(points, cells), **kw)
    return str(path)


def drone_cfg(path, rotors, dim=3, scale=1.0, num_sensors=None, **kw):
    """What make_file_shape reads of a DroneConfig."""
    return SimpleNamespace(dim=dim, mesh=SimpleNamespace(file=str(path), scale=scale), rotors=rotors,
                           rotor_normals=kw.get("rotor_normals", []), imus=kw.get("imus", []),
                           num_sensors=len(rotors) if num_sensors is None else num_sensors,
                           rotor_radius=kw.get("radius", 0.2), imu_radius=kw.get("radius", 0.2))


# ------------------------------------------------------------------ reading

@pytest.mark.parametrize("suffix", ["stl", "obj", "ply", "off", "vtu", "msh"])
def test_every_format_gives_the_same_body_in_metres(tmp_path, suffix):
    v, f = box()
    path = write(tmp_path / f"box.{suffix}", v * 1000, [("triangle", f)],
                 **({"file_format": "gmsh22", "binary": False} if suffix == "msh" else {}))
    body = read_body(path, 3, 0.001)
    assert np.allclose(body.extent, [2.0, 0.2, 1.0])
    assert enclosed_volume(body.vertices, body.faces) == pytest.approx(0.4)
    assert body.elems is None


def test_an_inward_surface_is_turned_outward_and_quads_are_split(tmp_path):
    v, f = box()
    quads = f.reshape(-1, 2, 3)[:, 0]   # (a, b, c) of each (a, b, c, d) quad ...
    quads = np.c_[quads, f.reshape(-1, 2, 3)[:, 1, 2]]   # ... and its d
    body = read_body(write(tmp_path / "in.vtu", v, [("quad", quads[:, ::-1])]), 3, 1.0)
    assert len(body.faces) == 12 and enclosed_volume(body.vertices, body.faces) == pytest.approx(0.4)


def test_a_tet_mesh_is_used_as_given(tmp_path):
    v, _ = box()
    tets = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    body = read_body(write(tmp_path / "box.vtu", v, [("tetra", tets)]), 3, 1.0)
    assert body.elems is not None and len(body.elems) == 6
    pts, el = clean_tets(v, tets)
    assert np.array_equal(body.elems, el) and np.allclose(body.vertices, pts)
    assert enclosed_volume(body.vertices, body.faces) == pytest.approx(0.4)   # its boundary, outward


def test_2d_outlines_from_text_lines_and_triangle_meshes_agree(tmp_path):
    square = np.array([[0, 0], [2, 0], [2, 1], [0, 1]], float)
    np.savetxt(tmp_path / "sq.txt", square[::-1])   # clockwise: turned counter-clockwise
    hole = np.array([[0.5, 0.25], [0.5, 0.75], [1.0, 0.75], [1.0, 0.25]])
    pts = np.r_[square, hole]
    lines = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4]])
    text = read_body(str(tmp_path / "sq.txt"), 2, 1.0)
    assert enclosed_volume(text.vertices, text.faces) == pytest.approx(2.0) and len(text.holes) == 0
    ring = read_body(write(tmp_path / "ring.vtk", np.c_[pts, np.zeros(8)], [("line", lines)]), 2, 1.0)
    assert enclosed_volume(ring.vertices, ring.faces) == pytest.approx(2.0 - 0.25)
    (hx, hy), = ring.holes
    assert 0.5 < hx < 1.0 and 0.25 < hy < 0.75   # a point in the hole, for Triangle
    t = triangle.triangulate({"vertices": pts, "segments": lines, "holes": [[0.75, 0.5]]}, "pq")
    tri = read_body(write(tmp_path / "tri.vtu", np.c_[t["vertices"], np.zeros(len(t["vertices"]))],
                          [("triangle", t["triangles"])]), 2, 1.0)
    assert enclosed_volume(tri.vertices, tri.faces) == pytest.approx(1.75) and len(tri.holes) == 1


# ------------------------------------------------------------------ bodies that are not bodies

@pytest.mark.parametrize("spoil, words", [
    (lambda v, f: (v, f[1:]), "not closed"),
    (lambda v, f: (v, np.r_[f[:1, [0, 2, 1]], f[1:]]), "not consistently oriented"),
    (lambda v, f: (v, np.array([[0, 1, 3], [0, 3, 1]])), "zero volume"),   # closed, but flat: a sheet
])
def test_a_surface_that_bounds_no_solid_is_refused(tmp_path, spoil, words):
    v, f = spoil(*box())
    with pytest.raises(UserError, match=words) as info:
        read_body(write(tmp_path / "bad.stl", v, [("triangle", f)]), 3, 1.0)
    assert "drone.mesh.file = bad.stl" in str(info.value)


def test_unreadable_and_missing_files_name_the_file_and_the_formats(tmp_path):
    (tmp_path / "junk.stl").write_bytes(b"\x00\x01 not a mesh")
    for path in (tmp_path / "junk.stl", tmp_path / "none.stl"):
        with pytest.raises(UserError) as info:
            read_body(str(path), 3, 1.0)
        assert path.name in str(info.value) and "STL, OBJ, PLY" in str(info.value)


def test_an_open_2d_outline_is_refused(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0]], float)
    with pytest.raises(UserError, match="outline is not closed"):
        read_body(write(tmp_path / "open.vtk", pts, [("line", np.array([[0, 1], [1, 2]]))]), 2, 1.0)


# ------------------------------------------------------------------ snapping and placing

def test_closest_points_are_the_nearest_of_each_triangle():
    rng = np.random.default_rng(0)
    v, f = box()
    q = rng.normal(size=3)
    near = closest_points(v, f, q)
    for k, (a, b, c) in enumerate(v[f]):   # against dense samples of each triangle
        u, w = np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60))
        keep = (u + w <= 1).ravel()
        samples = a + np.c_[u.ravel(), w.ravel()][keep] @ np.array([b - a, c - a])
        assert np.linalg.norm(near[k] - q) <= np.linalg.norm(samples - q, axis=1).min() + 1e-9


def test_a_rotor_snaps_along_the_normal_onto_the_surface_that_faces_its_way():
    v, f = box()
    anchor, normal, dist = snap(v, f, np.array([0.3, 0.25, 0.2]), np.array([0.0, 1.0, 0.0]), 0.2)
    assert np.allclose(anchor, [0.3, 0.1, 0.2]) and np.allclose(normal, [0, 1, 0]) and dist == pytest.approx(0.15)
    # listed below the body with +Y: still the upper surface, not the nearer bottom
    anchor, _, _ = snap(v, f, np.array([0.3, -0.15, 0.2]), np.array([0.0, 1.0, 0.0]), 0.2)
    assert np.allclose(anchor, [0.3, 0.1, 0.2])


def test_the_tripod_places_its_rotors_on_top_and_an_imu_on_each_arm():
    shape = make_file_shape(drone_cfg("tripod.stl", TRIPOD, scale=0.001, num_sensors=3))
    assert np.allclose(shape.rotors, TRIPOD, atol=1e-9) and np.allclose(shape.rotor_normals, [0, 1, 0])
    assert np.allclose(shape.imus[:, 1], 0.1) and np.allclose(shape.frame_imus[:, 1], 0.1)
    centre = enclosed_centroid(shape.vertices, shape.faces)
    assert np.allclose(shape.center, centre)
    arms = np.array(TRIPOD)[1:, [0, 2]] - centre[[0, 2]]
    directions = (shape.imus[:, [0, 2]] - centre[[0, 2]]) @ arms.T
    cos = directions / np.linalg.norm(shape.imus[:, [0, 2]] - centre[[0, 2]], axis=1)[:, None] \
        / np.linalg.norm(arms, axis=1)
    assert sorted(np.argmax(cos, axis=1)) == [0, 1, 2] and cos.max(axis=1).min() > 0.99   # one per arm


def test_listed_normals_and_imus_are_taken_as_given(tmp_path):
    v, f = box()
    path = write(tmp_path / "b.stl", v, [("triangle", f)])
    rotors = [[-0.8, 0.1, 0.0], [0.8, 0.1, 0.0], [0.0, 0.1, 0.4], [1.0, 0.0, 0.0]]
    normals = [[0, 1, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0]]   # the last on the +X end, pushing along +X
    shape = make_file_shape(drone_cfg(path, rotors, rotor_normals=normals, imus=[[0.5, 0.1, 0.3]], num_sensors=1))
    assert np.allclose(shape.rotors[3], [1.0, 0.0, 0.0]) and np.allclose(shape.rotor_normals[3], [1, 0, 0])
    assert np.allclose(shape.imus, [[0.5, 0.1, 0.3]])


@pytest.mark.parametrize("rotors, kw, words", [
    ([[0, 0.1, 0], [0.5, 0.1, 0], [3.0, 0.1, 0.0]], {}, "drone.rotors[2] = [3.0, 0.1, 0.0] is off the body"),
    ([[0, 0.1, 0], [0.5, 0.1, 0], [0.9, 0.1, 0.0]], {}, "lie on one line"),
    ([[0, 0.1, 0], [0.5, 0.1, 0], [0, 0.1, 0.4]], {"imus": [[0.2, 0.9, 0.2]], "num_sensors": 1},
     "drone.imus[0] = [0.2, 0.9, 0.2] is off the body"),
])
def test_rotors_and_imus_off_the_body_are_refused(tmp_path, rotors, kw, words):
    v, f = box()
    path = write(tmp_path / "b.stl", v, [("triangle", f)])
    with pytest.raises(UserError) as info:
        make_file_shape(drone_cfg(path, rotors, **kw))
    assert words in str(info.value)


def test_a_ring_whose_centre_is_a_hole_cannot_place_its_frame_imu(tmp_path):
    v, f = extruded([circle(1.5), circle(1.0, cw=True)], holes=[(0.0, 0.0)])
    path = write(tmp_path / "ring.stl", v, [("triangle", f)])
    rotors = [[1.25, 0.1, 0.0], [-1.25, 0.1, 0.0], [0.0, 0.1, 1.25]]
    with pytest.raises(UserError, match="the placement rule puts the frame IMU") as info:
        make_file_shape(drone_cfg(path, rotors))
    assert "drone.imus" in str(info.value)


def test_the_tripod_config_validates_and_its_caches_follow_the_file_content(tmp_path, monkeypatch):
    import hashlib
    import shutil

    from sdexp.config import mesh_path
    from sdexp.eval.run import preflight, typed
    from tests.conftest import make_cfg
    cfg = make_cfg("drone=tripod")
    preflight(cfg)
    shipped = typed(cfg).drone.mesh.digest
    assert shipped == hashlib.sha256(mesh_path("tripod.stl").read_bytes()).hexdigest()[:16]
    # the same name in the working directory, other bytes: another digest, so other cache keys
    monkeypatch.chdir(tmp_path)
    v, f = box()
    meshio.write(tmp_path / "tripod.stl", meshio.Mesh(v, [("triangle", f)]))
    assert typed(make_cfg("drone=tripod")).drone.mesh.digest not in (None, shipped)
    shutil.copy(tmp_path / "tripod.stl", tmp_path / "copy.stl")
    assert typed(make_cfg("drone=tripod", "drone.mesh.file=copy.stl")).drone.mesh.digest == \
        typed(make_cfg("drone=tripod")).drone.mesh.digest   # a renamed copy shares them
