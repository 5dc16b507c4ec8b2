"""Plates meshed by extrusion (drone.mesh.layers >= 1): valid, conforming, exact in thickness,
exactly symmetric when mirrored, and as accurate as a converged mesh with quadratic elements."""
from dataclasses import replace

import numpy as np
import pytest

from sdexp import conf
from sdexp.cache import config_key
from sdexp.config import MeshConfig
from sdexp.sim.drone import make_shape, mesh_shape
from sdexp.sim.mesh.surface import boundary_faces, face_normals

from tests.sim.test_mirror import mirror_gap


def layered(name, tmp_path, **mesh):
    cfg = conf.drone(name)
    cfg = replace(cfg, mesh=replace(cfg.mesh, **mesh))
    return mesh_shape(make_shape(cfg), cfg.mesh, str(tmp_path))


@pytest.mark.parametrize("layers", [1, 2])
def test_flat_plate_extrusion_is_valid_and_conforming(tmp_path, layers):
    """Every tet positive; the only faces with one tet are the caps (normal along y) and the
    walls (normal in x-z): a prism cut inconsistently with its neighbour would leave an inner
    face, oblique, on one side only. The volume is the caps' area times the thickness."""
    pts, tets = layered("flower", tmp_path, edge_length=0.3, layers=layers)
    d = pts[tets[:, 1:]] - pts[tets[:, :1]]
    vol = np.linalg.det(d) / 6
    assert np.all(vol > 1e-9)
    faces = boundary_faces(tets)
    n = face_normals(pts, faces)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cap = np.abs(n[:, 1]) > 1 - 1e-9
    assert np.all(cap | (np.abs(n[:, 1]) < 1e-9))
    top = faces[cap & (n[:, 1] > 0)]
    area = np.linalg.norm(face_normals(pts, top), axis=1).sum()
    assert vol.sum() == pytest.approx(area * 0.225, rel=1e-9)
    assert len(np.unique(np.round(pts[:, 1], 9))) == layers + 1


def test_mirrored_extrusion_is_exactly_symmetric_and_follows_the_taper(tmp_path):
    """The star (mirror [x, z], a thick pod and thin arms): the mesh maps onto itself across
    both planes, and the thickness follows the design (0.375 m pod, 0.15 m arms)."""
    pts, tets = layered("star", tmp_path, layers=1)
    mids = pts[tets].mean(axis=1)    # the elements mirror too, not only the nodes
    for p in (pts, mids):
        assert mirror_gap(p, 0) < 1e-12 and mirror_gap(p, 2) < 1e-12
    columns = {}
    for p in pts:
        columns.setdefault((round(p[0], 9), round(p[2], 9)), []).append(p[1])
    thickness = np.array([max(v) - min(v) for v in columns.values()])
    assert thickness.max() == pytest.approx(0.375, rel=1e-6) and thickness.min() == pytest.approx(0.15, rel=1e-3)


def test_layers_key_and_bad_input(tmp_path):
    assert config_key(MeshConfig(layers=2))["layers"] == 2 != config_key(MeshConfig())["layers"]
    from sdexp.errors import UserError
    rod = conf.drone("rod")
    rod = replace(rod, mesh=replace(rod.mesh, layers=1))
    with pytest.raises(UserError, match="drone.mesh.layers"):
        mesh_shape(make_shape(rod), rod.mesh, str(tmp_path))


def test_exact_outline_keeps_the_notches_that_an_even_resampling_cuts(tmp_path):
    """drone.mesh.outline: exact (the converged references' meshes). The flower's petals meet
    the disc in narrow notches (1 deg of arc at 0.60 m from the centre): resampled evenly (edge
    0.35 m / 1, 1.5, 2, 3) the outline runs across them and the mesh fills them to 0.63-0.69 m
    from the centre with material the design does not have; the exact outline reaches the notch
    bottoms, its segments graded finer there."""
    def notch_bottom(pts, tets):   # the outline's nearest point to the centre between two petals
        faces = boundary_faces(tets)
        n = face_normals(pts, faces)
        wall = np.unique(faces[np.abs(n[:, 1]) < 1e-9 * np.linalg.norm(n, axis=1)])
        ang, r = np.arctan2(pts[wall, 2], pts[wall, 0]), np.hypot(pts[wall, 0], pts[wall, 2])
        return r[np.abs(ang - np.pi / 8) < np.radians(5)].min()   # between the petals along 0 and 45 deg
    cut = notch_bottom(*layered("flower", tmp_path, edge_length=0.35 / 1.5, layers=2))
    kept = notch_bottom(*layered("flower", tmp_path, edge_length=0.35 / 1.5, layers=2, outline="exact"))
    assert cut > 0.62 and kept == pytest.approx(0.600, abs=1e-3)
    assert config_key(MeshConfig()) == config_key(MeshConfig(outline="resampled"))   # old caches stay valid
    assert config_key(MeshConfig(outline="exact")) != config_key(MeshConfig())
