"""Pictures of a flight in motion (sdexp.eval.animation): a recorded flight becomes a video the
readers can open and a VTU series ParaView can (meshio reads it back, the .pvd lists every
frame); recording leaves the flight's numbers bit for bit as they are."""
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from sdexp.control.rollout import FrameRecorder, fly, metrics
from sdexp.eval import animation
from sdexp.eval.run import run_experiment
from tests.eval.references import reduced_overrides
from sdexp.sim.mesh.surface import boundary_faces
from sdexp.sim.physics.quadratic import quadratic_mesh
from tests.conftest import make_cfg, make_config

imageio = pytest.importorskip("imageio.v3")
meshio = pytest.importorskip("meshio")


def cube_mesh():
    """A unit cube in 6 positively oriented tets (points, elems)."""
    pts = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    elems = np.array([[0, 4, 6, 7], [0, 4, 5, 7], [0, 1, 5, 7], [0, 1, 3, 7], [0, 2, 3, 7], [0, 2, 6, 7]])
    for e in elems:
        a, b, c, dd = pts[e]
        if np.linalg.det(np.c_[b - a, c - a, dd - a]) < 0:
            e[[1, 2]] = e[[2, 1]]
    return pts, elems


def moving(rest, n, dt=0.04):
    """A body flying up and sideways, turning and bending (its top pulled out)."""
    t = np.arange(n) * dt
    frames = []
    for tt in t:
        c, s = np.cos(0.5 * tt), np.sin(0.5 * tt)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        bend = np.c_[0.1 * np.sin(tt) * rest[:, 1], np.zeros(len(rest)), np.zeros(len(rest))]
        frames.append((rest + bend) @ rot.T + np.array([0.5 * tt, 0.3 * tt, 0.0]))
    return np.stack(frames), t


def test_a_3d_animation_with_obstacles_is_a_readable_video(tmp_path):
    pts, elems = cube_mesh()
    frames, t = moving(pts, 12)
    boxes = [{"min": [0.8, -1.0, 0.5], "max": [1.2, 3.0, 2.0]}, ([0.8, -1.0, -2.0], [1.2, 3.0, -0.5])]
    path = animation.write_animation(tmp_path / "cube.mp4", frames, t, boundary_faces(elems), rest=pts,
                                     obstacles=boxes, title="cube", progress=False)
    assert path == tmp_path / "cube.mp4"
    video = imageio.imread(path)
    assert video.shape == (12, animation.SIZE[1], animation.SIZE[0], 3)
    assert video[0].std() > 0 and np.abs(video[-1].astype(int) - video[0]).mean() > 0.1   # it moves


def test_without_ffmpeg_the_animation_is_a_gif(tmp_path, monkeypatch):
    monkeypatch.setattr(animation, "_ffmpeg_available", lambda: False)
    pts, elems = cube_mesh()
    frames, t = moving(pts, 5)
    path = animation.write_animation(tmp_path / "cube.mp4", frames, t, boundary_faces(elems), color="height",
                                     view="follow", progress=False)
    assert path == tmp_path / "cube.gif" and not (tmp_path / "cube.mp4").exists()
    gif = imageio.imread(path, index=None)
    assert gif.shape[:3] == (5, animation.SIZE[1] // 2, animation.SIZE[0] // 2)


def test_a_vtu_series_reads_back_with_every_frame_in_its_pvd(tmp_path):
    pts, elems = quadratic_mesh(*cube_mesh())                       # 10-node tets, VTK order
    frames, t = moving(pts, 4)
    disp = frames - animation.rigid_fit(frames, pts)
    pvd = animation.write_vtu_series(tmp_path / "cube_vtu", frames, elems, t, point_data={"deformation": disp})
    listed = animation.read_pvd(pvd)
    assert [time for time, _ in listed] == pytest.approx(list(t))
    assert len({f for _, f in listed}) == 4
    assert ET.parse(pvd).getroot().get("type") == "Collection"
    for i, (_, name) in enumerate(listed):
        mesh = meshio.read(pvd.parent / name)
        assert mesh.points.shape == (len(pts), 3) and np.array_equal(mesh.points, frames[i])
        assert mesh.cells_dict["tetra10"].shape == elems.shape
        assert np.array_equal(mesh.point_data["deformation"], disp[i])
    # 2D points (6-node triangles) get z = 0; a shorter series written over a longer one leaves
    # no stray frames
    sq, tri = quadratic_mesh(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]),
                             np.array([[0, 1, 2], [0, 2, 3]]))
    flat = animation.write_vtu_series(tmp_path / "cube_vtu", [sq, sq + 1.0], tri, [0.0, 0.1])
    assert len(list((tmp_path / "cube_vtu").glob("*.vtu"))) == 2 and len(animation.read_pvd(flat)) == 2
    back = meshio.read(tmp_path / "cube_vtu" / "cube_vtu_00001.vtu")
    assert np.array_equal(back.points, np.c_[sq + 1.0, np.zeros(len(sq))]) and "triangle6" in back.cells_dict


def test_the_rigid_fit_leaves_no_deformation_in_a_rigid_motion():
    pts, _ = cube_mesh()
    c, s = np.cos(1.0), np.sin(1.0)
    moved = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + 2.0
    assert animation.deformation(moved[None], pts).max() < 1e-12
    assert animation.deformation((pts * [1.0, 1.1, 1.0])[None], pts).max() > 0.01


def test_recording_keeps_a_flight_bit_for_bit(cache_dir):
    """The same noisy flight (rigid LQR on the rod, 0.3 s) with and without a recorder."""
    from sdexp.control.tasks import Task
    from sdexp.eval import controllers
    from sdexp.sim.drone import build_drone
    from sdexp.sim.simulator import Simulator

    cfg = make_config("drone=rod", f"cache_dir={cache_dir}", "sim.threads=1")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    runs = []
    for rec in (None, FrameRecorder(25.0)):
        sim = Simulator(drone, cfg.sim, cfg.noise, seed=3)
        ctl = controllers.build("rigid_lqr", cfg, sim)
        task = Task(start=np.zeros(2), target=np.array([1.0, 1.0]), seconds=0.3, n_s=drone.layout.n_s)
        flight = fly(sim, ctl, task, recorder=rec)
        n_s = drone.layout.n_s
        m = metrics(flight, slice(2 * n_s + 2, 2 * n_s + 4), slice(2 * n_s, 2 * n_s + 1), 0.3)
        runs.append((flight, m, sim.x.copy(), rec))
    (a, ma, xa, _), (b, mb, xb, rec) = runs
    for k in ("t", "x", "u", "goal"):
        assert np.array_equal(a.arrays()[k], b.arrays()[k]), k
    assert ma == mb and np.array_equal(xa, xb)
    assert rec.every == 4 and rec.times[:3] == pytest.approx([0.0, 0.04, 0.08])
    assert rec.times[-1] == a.t[-1] and np.array_equal(rec.points[-1], xa)
    assert len(rec.points) == len(rec.times) == 9                      # 0, 0.04, ..., 0.28, 0.3


def test_the_hover_deform_runner_writes_its_animation_and_its_numbers_do_not_change(tmp_path, cache_dir):
    over = reduced_overrides("hover_deform", cache_dir)
    on = run_experiment(make_cfg(*over, "experiment.params.paraview=true"), tmp_path / "on")
    off = run_experiment(make_cfg(*over, "experiment.params.animate=false"), tmp_path / "off")
    video_only = run_experiment(make_cfg(*over), tmp_path / "video_only")   # the default: no ParaView series
    assert (tmp_path / "video_only" / "hover_deform.mp4").exists()
    assert not (tmp_path / "video_only" / "hover_deform_vtu").exists() and video_only == off
    assert json.dumps(on, sort_keys=True) == json.dumps(off, sort_keys=True)   # bit for bit
    assert not list((tmp_path / "off").glob("*.mp4")) and not (tmp_path / "off" / "hover_deform_vtu").exists()
    # 0.26 s at 25 frames/s: 0, 0.04, ..., 0.24 and the last state at 0.26
    video = imageio.imread(tmp_path / "on" / "hover_deform.mp4")
    assert video.shape == (8, animation.SIZE[1], animation.SIZE[0], 3)
    pvd = tmp_path / "on" / "hover_deform_vtu" / "hover_deform.pvd"
    listed = animation.read_pvd(pvd)
    assert len(listed) == 8 and listed[-1][0] == pytest.approx(0.26)
    cfg = make_config(*over)
    from sdexp.sim.drone import build_drone
    nv = len(build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element).fem.rest)
    for _, name in listed:
        mesh = meshio.read(pvd.parent / name)
        assert mesh.points.shape == (nv, 3) and "triangle6" in mesh.cells_dict


def test_whether_a_flight_is_drawn_is_not_part_of_what_a_run_computes(tmp_path):
    """A finished run is reused with animate switched, and sweeps do not group jobs by it."""
    from omegaconf import OmegaConf
    from sdexp.eval.stats import _flat, group_jobs

    cfg = make_cfg("experiment=sota", "drone=rod")
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    (tmp_path / "metrics.json").write_text(json.dumps({"ours_survival_time": 20.0}))
    assert run_experiment(make_cfg("experiment=sota", "drone=rod", "experiment.params.animate=[]"),
                          tmp_path) == {"ours_survival_time": 20.0}
    configs = [_flat(OmegaConf.to_container(make_cfg("experiment=hover_deform", f"experiment.params.animate={a}")))
               for a in ("true", "false")]
    assert group_jobs(configs)[0] == []
