"""Mirror-symmetric meshes (drone.mesh.mirror): one cell of the design meshed, then reflected."""
import itertools

import numpy as np
import pytest

from sdexp.config import NoiseConfig
from sdexp.errors import UserError
from sdexp.sim.drone import build_drone, make_shape
from sdexp.sim.mesh.surface import boundary_faces
from sdexp.sim.rigid.geometry import deformation_patterns, rest_hover_thrust
from sdexp.sim.mesh.mirror import reflect
from sdexp.sensing import decompose
from sdexp.sim.simulator import Simulator
from sdexp.sim.rigid.statics import outer_rotors
from tests.sim.test_shapes3d import surface_volume
from tests.conftest import make_config as make_cfg


def volumes(points, tets):
    return np.linalg.det(points[tets[:, 1:]] - points[tets[:, :1]]) / 6.0


def mirror_gap(points, axis):
    """Largest distance from a point reflected across coordinate ``axis`` = 0 to the nearest point."""
    flipped = points * np.where(np.arange(3) == axis, -1.0, 1.0)
    return np.min(np.linalg.norm(flipped[:, None] - points[None], axis=2), axis=1).max()


def unit_cube():
    """[0, 1]^3 in Kuhn's six tets, positively oriented."""
    corners = np.array(list(itertools.product((0.0, 1.0), repeat=3)))
    index = {tuple(c): i for i, c in enumerate(corners)}
    tets = []
    for order in itertools.permutations(range(3)):
        path, p = [index[(0.0, 0.0, 0.0)]], np.zeros(3)
        for axis in order:
            p = p.copy()
            p[axis] = 1.0
            path.append(index[tuple(p)])
        tets.append(path)
    tets = np.array(tets)
    flip = volumes(corners, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return corners, tets


def test_reflect_glues_a_cube_to_its_mirror_image():
    points, tets = unit_cube()
    points[points[:, 0] == 0, 0] = 2e-4         # the cut off its plane by a mesher's tolerance
    glued, glued_tets = reflect(points, tets, 0, tol=1e-2)
    assert len(glued) == 8 + 4 and len(glued_tets) == 12
    assert np.all(volumes(glued, glued_tets) > 0)
    assert volumes(glued, glued_tets).sum() == pytest.approx(2.0)
    assert len(boundary_faces(glued_tets)) == 2 * 12 - 2 * 2   # the two cut triangles are inside
    assert mirror_gap(glued, 0) == 0.0


def test_reflect_refuses_a_cell_that_crosses_its_plane():
    points, tets = unit_cube()
    points[:, 0] -= 0.5
    with pytest.raises(ValueError, match="no boundary face|crosses"):
        reflect(points, tets, 0, tol=1e-2)


@pytest.fixture(scope="module")
def star(cache_dir):
    """The committed star (conf/drone/star.yaml: thin arms, drone.mesh.mirror = [x, z])."""
    cfg = make_cfg("drone=star", f"cache_dir={cache_dir}")
    assert list(cfg.drone.mesh.mirror) == ["x", "z"]
    return cfg, build_drone(cfg.drone, cache_dir, cfg.sim.element)


def test_a_mirrored_mesh_is_the_design_reflected_onto_itself(star):
    cfg, drone = star
    rest = drone.fem.rest
    assert mirror_gap(rest, 0) < 1e-12 and mirror_gap(rest, 2) < 1e-12
    shape = make_shape(cfg.drone)
    assert drone.fem.vol.sum() == pytest.approx(surface_volume(shape.vertices, shape.faces), rel=0.01)
    assert np.all(drone.fem.vol > 0)


@pytest.mark.parametrize("drone, planes", [("donut", "[x,z]"), ("orange_peel", "[x]")])
def test_a_ring_and_a_bowl_mirror_too(cache_dir, drone, planes):
    """The hole of the donut (chords only through the ring) and the orange peel's curved bowl,
    symmetric about x = 0 only (five petals)."""
    cfg = make_cfg(f"drone={drone}", f"drone.mesh.mirror={planes}", f"cache_dir={cache_dir}")
    rest = build_drone(cfg.drone, cache_dir, cfg.sim.element).fem.rest
    for name in planes.strip("[]").split(","):
        assert mirror_gap(rest, {"x": 0, "z": 2}[name]) < 1e-12


def test_a_mirrored_star_folds_both_wings_alike_and_does_not_yaw(star):
    """A mirror-symmetric body under a mirror-symmetric load: no yaw torque, equal folds (the
    whole-body fTetWild mesh of an even 0.15 m star yawed 1-3 deg/s so, its wings at 71 and 77 deg)."""
    cfg, drone = star
    null = deformation_patterns(drone)
    pattern = null @ (null.T @ outer_rotors(drone, along_z=True).astype(float))
    u = rest_hover_thrust(drone, float(cfg.sim.gravity)) + 4.0 * pattern / np.abs(pattern).max()
    sim = Simulator(drone, cfg.sim, NoiseConfig(enabled=False), seed=0)
    sim.reset()
    for _ in range(100):
        r = sim.step(u)
    st = decompose(r, drone.layout)
    assert np.rad2deg(st.s[[1, 3]]).min() > 30.0               # the Z wings fold
    assert st.s[1] == pytest.approx(st.s[3], abs=1e-6) and st.s[0] == pytest.approx(st.s[2], abs=1e-6)
    assert abs(st.e[1]) < 1e-6 and abs(st.e_dot[1]) < 1e-6       # yaw, about +Y


def test_mirroring_a_design_that_is_not_symmetric_names_the_key(cache_dir):
    cfg = make_cfg("drone=orange_peel", "drone.mesh.mirror=[z]", f"cache_dir={cache_dir}")
    with pytest.raises(UserError, match=r"drone\.mesh\.mirror.*rotors"):
        build_drone(cfg.drone, cache_dir, cfg.sim.element)
