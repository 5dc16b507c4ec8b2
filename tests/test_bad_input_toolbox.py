"""Bad input on the researcher's toolbox (issue 53): a drone's mesh file that is no solid body,
rotors and IMUs that do not fit it, a bad action to a Gymnasium environment, a misspelled
config choice, and the documented commands doing what they say. As in test_bad_input.py: one
line naming the file or key and what is wrong, exit code 2 on the command line, nothing written.
No test meshes with fTetWild: every mesh-file case is refused before meshing."""
import builtins
import logging
import os

import meshio
import numpy as np
import pytest

from sdexp.errors import UserError
from sdexp.sim.mesh.meshfile import read_body
from sdexp.sim.mesh.surface import enclosed_volume
from tests.sim.test_meshfile import box, drone_cfg
from tests.test_bad_input import ON_BOX, assert_one_line_error, rejected, sdexp


def _stl(folder, name, v, f):
    with np.errstate(invalid="ignore", divide="ignore"):   # meshio's facet normals of flat or NaN triangles
            meshio.write(folder / name, meshio.Mesh(np.asarray(v, float), [("triangle", np.asarray(f))]))


def _pushed_through(v):
    """The box with a top corner pushed down through the bottom face: closed, one piece, crossing."""
    v = v.copy()
    v[0] = [0.5, 0.5, 0.0]
    return v


@pytest.fixture
def meshes(tmp_path, monkeypatch):
    """Bad mesh files, in a working directory of their own (relative files are read from it)."""
    v, f = box()
    (tmp_path / "empty.stl").write_bytes(b"")
    (tmp_path / "folder.stl").mkdir()
    _stl(tmp_path, "flat.stl", v * [1, 0, 1], f)                          # closed, but flat: no volume
    _stl(tmp_path, "wall.stl", np.r_[v, v + [2, 0.2, 0]], np.r_[f, f + 8])   # two boxes sharing an edge
    _stl(tmp_path, "pinched.stl", np.r_[v, v + [2, 0.2, 1]], np.r_[f, f + 8])   # ... sharing a corner
    _stl(tmp_path, "crossing.stl", _pushed_through(v), f)
    _stl(tmp_path, "two.stl", np.r_[v, v + [3, 0, 0]], np.r_[f, f + 8])    # two bodies apart
    for bad in ("nan", "inf"):
        w = v.copy()
        w[5, 1] = float(bad)
        _stl(tmp_path, f"{bad}.stl", w, f)
    _stl(tmp_path, "inward.stl", v, f[:, ::-1])
    _stl(tmp_path, "box.stl", v, f)
    _stl(tmp_path, "thick.stl", v * [1, 5, 1], f)                          # 1 m thick: room inside
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("file, words", [
    ("empty.stl", "empty.stl: the file is empty (0 bytes)"),
    ("folder.stl", "'folder.stl' is a folder"),
    ("flat.stl", "flat.stl: the surface encloses zero volume"),
    ("wall.stl", "wall.stl: the surface is non-manifold (1 edges border more than two triangles)"),
    ("pinched.stl", "pinched.stl: the surface is non-manifold at 1 vertices"),
    ("crossing.stl", "crossing.stl: the surface intersects itself"),
    ("two.stl", "two.stl: the surface is 2 separate bodies"),
    ("nan.stl", "nan.stl: 4 of its 11 vertices are NaN or infinite (vertex 7: [1.0, nan, 0.5])"),   # NaN != NaN: STL's
    ("inf.stl", "inf.stl: 1 of its 8 vertices are NaN or infinite (vertex 7: [1.0, inf, 0.5])"),    # copies stay apart
])
def test_a_mesh_file_that_is_no_solid_body_is_refused_by_name(meshes, file, words):
    message = rejected("drone=custom", f"drone.mesh.file={file}", ON_BOX)
    assert words in message and len(message.splitlines()) == 1, message


def test_a_2d_outline_of_two_bodies_is_refused(tmp_path):
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    ring = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    path = tmp_path / "two.vtk"
    meshio.write(path, meshio.Mesh(np.r_[square, square + [2, 0, 0]], [("line", np.r_[ring, ring + 4])]))
    with pytest.raises(UserError, match="two.vtk: the outline is 2 separate bodies"):
        read_body(str(path), 2, 1.0)


def test_an_unreadable_mesh_file_is_refused_by_name(meshes, monkeypatch):
    path = meshes / "box.stl"
    path.chmod(0)
    if os.access(path, os.R_OK):   # root reads it anyway: the error a user without the right meets
        real = builtins.open

        def refuse(file, *args, **kw):
            if str(file) == str(path):
                raise PermissionError(13, "Permission denied", str(file))
            return real(file, *args, **kw)
        monkeypatch.setattr(builtins, "open", refuse)
    message = rejected("drone=custom", "drone.mesh.file=box.stl", ON_BOX)
    assert "drone.mesh.file = box.stl: cannot read it (Permission denied)" in message, message


def test_an_inward_facing_stl_is_turned_outward_and_says_so(meshes, caplog):
    """Inverted normals are flipped, not refused: a closed, consistently oriented surface has one
    inside, and CAD tools export either winding (docs/toolbox.md)."""
    with caplog.at_level(logging.INFO, logger="sdexp.sim.mesh.meshfile"):
        body = read_body(str(meshes / "inward.stl"), 3, 1.0)
    assert enclosed_volume(body.vertices, body.faces) == pytest.approx(0.4)
    assert "inward.stl: its triangles face inward" in caplog.text


def test_a_shipped_and_a_crossing_surface_are_told_apart():
    """The self-intersection test finds the crossing box and none in the shipped tripod."""
    from sdexp.config import mesh_path
    from sdexp.sim.mesh.topology import crossing_pairs
    v, f = box()
    assert len(crossing_pairs(v, f)) == 0 and len(crossing_pairs(_pushed_through(v), f)) > 0
    read_body(str(mesh_path("tripod.stl")), 3, 0.001)   # no error


@pytest.mark.parametrize("overrides, words", [
    ("drone.mesh.file=thick.stl drone.rotors=[[0,0,0],[0.8,0.5,0],[0,0.5,0.4]]",
     "drone.rotors[0] = [0.0, 0.0, 0.0] is inside the body of thick.stl: the nearest surface facing [0.0, 1.0, 0.0] "
     "is 0.5 m away"),
    ("drone.mesh.file=thick.stl drone.rotors=[[0,3,0],[0.8,0.5,0],[0,0.5,0.4]]",
     "drone.rotors[0] = [0.0, 3.0, 0.0] is off the body of thick.stl"),
    (f"drone.mesh.file=box.stl {ON_BOX} drone.rotor_normals=[[0,0,0]]",   # zero, and one for three rotors
     "drone.rotor_normals[0] = [0, 0, 0] is zero: allowed a non-zero direction"),
])
def test_rotors_inside_or_off_the_body_and_zero_normals_are_refused(meshes, overrides, words):
    message = rejected("drone=custom", *overrides.split())
    assert words in message, message


def test_more_imus_than_the_rule_can_place_stop_before_meshing():
    message = rejected("drone=tripod", "drone.num_sensors=50")
    assert "drone.num_sensors = 50: the placement rule puts IMUs 0.0539 m apart on tripod.stl" in message
    assert "allowed at most 12 on these rotors, or list them in drone.imus" in message, message


def test_the_rule_places_as_many_imus_as_it_allows():
    from sdexp.sim.mesh.shapes.from_file import make_file_shape
    from tests.sim.test_meshfile import TRIPOD
    assert len(make_file_shape(drone_cfg("tripod.stl", TRIPOD, scale=0.001, num_sensors=12)).imus) == 12
    with pytest.raises(UserError, match="allowed at most 12"):
        make_file_shape(drone_cfg("tripod.stl", TRIPOD, scale=0.001, num_sensors=13))


@pytest.mark.parametrize("args, words", [
    (["drone=custom", "drone.mesh.file=empty.stl", ON_BOX], ["drone.mesh.file = empty.stl: the file is empty"]),
    (["drone=tripod", "drone.num_sensors=50"], ["drone.num_sensors = 50", "allowed at most 12"]),
])
def test_a_bad_mesh_drone_on_the_command_line_is_one_line_and_leaves_no_run_folder(tmp_path, args, words):
    (tmp_path / "empty.stl").write_bytes(b"")
    assert_one_line_error(sdexp(*args, cwd=tmp_path), *words)
    assert [p.name for p in tmp_path.iterdir()] == ["empty.stl"]


# ------------------------------------------------------------------ a bad action to an environment

@pytest.fixture(scope="module")
def rod_env(cache_dir):
    from tests.envs.test_envs import make
    env = make("sdexp/Rod-Hover-v0", cache_dir)
    env.reset(seed=0)
    return env


@pytest.mark.parametrize("action, words", [
    (np.zeros(3), "action array([0., 0., 0.]) (ndarray, shape (3,), dtype float64)"),
    (2.5, "action 2.5 (float, shape (), dtype float64)"),
    ("up", "action 'up' (str, shape (), dtype <U2)"),
    ([1.0, [2.0, 3.0], 4.0, 5.0, 6.0], "(list of ragged rows)"),
    (None, "action None (NoneType, shape (), dtype object)"),
])
def test_a_bad_action_names_itself_and_the_space(action, words, rod_env):
    from sdexp.envs.env import BadAction
    env = rod_env
    with pytest.raises(BadAction) as info:
        env.step(action)
    message = str(info.value)
    assert isinstance(info.value, ValueError) and len(message.splitlines()) == 1, message
    assert words in message and "is not in the action space Box(-1.0, 1.0, (5,), float32)" in message, message
    assert "expected 5 rotor thrusts as fractions of Tmax = 10 N, a float array of shape (5,)" in message, message
    env.step(np.zeros((1, 5)))   # a batch of one is taken, as before


# ------------------------------------------------------------------ "did you mean" for a misspelled choice

@pytest.mark.parametrize("overrides, words", [
    (["drone=flwer"], "drone=flwer is unknown (did you mean drone=flower?): choose one of bunny, custom"),
    (["experiment=galery"], "experiment=galery is unknown (did you mean experiment=gallery?)"),
    (["noise=paperr"], "noise=paperr is unknown (did you mean noise=paper?): choose one of none, paper"),
    (["experiment=gallery", "experiment.params.drones=[flower,octopuss]"],
     "drone 'octopuss' is unknown (did you mean octopus?)"),
    (["experiment.params.controllers=[ours,rigid_lqx]"], "controller 'rigid_lqx' is unknown (did you mean rigid_lqr?)"),
    (["drone=zzz"], "drone=zzz is unknown: choose one of"),   # nothing close: no guess
])
def test_a_misspelled_choice_says_what_was_meant(overrides, words):
    message = rejected(*overrides)
    assert words in message, message


def test_a_misspelled_drone_on_the_command_line_says_what_was_meant(tmp_path):
    assert_one_line_error(sdexp("drone=flwer", cwd=tmp_path), "drone=flwer is unknown (did you mean drone=flower?)")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ documented commands do what they say

def test_the_custom_drone_configs_command_draws_the_custom_drone(tmp_path, monkeypatch):
    """conf/drone/custom.yaml's comment, run as far as the gallery's choice of drones (meshing the
    body would take fTetWild's time): it draws the file's drone, not the paper's twelve; without
    experiment.params.drones it stops before anything is written, naming the fix."""
    import shlex
    from importlib.resources import files

    from sdexp.eval.gallery import drawn
    from sdexp.eval.run import check_overrides_reach, preflight, typed
    from tests.conftest import make_cfg
    comment = (files("sdexp.conf") / "drone" / "custom.yaml").read_text().splitlines()
    args = shlex.split(next(line for line in comment if "sdexp experiment=" in line).split("sdexp", 1)[1])
    assert "experiment=gallery" in args and "drone=custom" in args
    v, f = box(3.0, 0.2, 3.0)   # body.stl: a plate the command's rotors sit on
    _stl(tmp_path, "body.stl", v, f)
    monkeypatch.chdir(tmp_path)
    cfg = make_cfg(*args)
    preflight(cfg)
    config = typed(cfg)
    check_overrides_reach(config, args)
    assert drawn(config.experiment.params) == ["custom"]
    without = [a for a in args if not a.startswith("experiment.params.drones")]
    with pytest.raises(UserError, match=r"drone=custom is not among the drones gallery runs .*"
                                        r"add experiment.params.drones=\[custom\]"):
        check_overrides_reach(typed(make_cfg(*without)), without)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["body.stl"]   # nothing written
