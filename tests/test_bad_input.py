"""Bad input never crashes and never passes silently (issue 16): every case below is a UserError
(or, on the command line, exit code 2 and one line) naming the key, file or column and what is
allowed, and nothing is written. The validation functions are called directly; a handful of
real ``sdexp`` processes check the exit code and the one-line message."""
import json
import os
import subprocess
import sys

import pytest
from hydra.errors import ConfigCompositionException

from sdexp import conf
from sdexp.cli import describe
from sdexp.errors import EXIT_USER_ERROR, UserError
from sdexp.eval.run import preflight, typed
from sdexp.experiment_params import PARAMS, names
from tests.conftest import make_cfg


def rejected(*overrides) -> str:
    """The one-line message of a config sdexp refuses: a composition error (a type the schema
    refuses) as the cli words it, else sdexp's checks (the preflight: validate, the simulator's
    checks, the params' ranges and options)."""
    try:
        cfg = make_cfg(*overrides)
    except ConfigCompositionException as err:
        return describe(err, list(overrides))
    with pytest.raises(UserError) as info:
        preflight(cfg)
        typed(cfg)
    return str(info.value)


# ------------------------------------------------------------------ config: keys and values

@pytest.mark.parametrize("override, key, allowed", [
    # typos appended past the schema with Hydra's "+"
    ("+drone.youngs_modulos=5000", "drone.youngs_modulos", "did you mean drone.youngs_modulus"),
    ("+foo=1", "foo", "the keys of the config are"),
    ("+drone.mesh.edge_lenght=0.2", "drone.mesh.edge_lenght", "did you mean drone.mesh.edge_length"),
    ("+sim.gravty=9.81", "sim.gravty", "did you mean sim.gravity"),
    ("+control.neural.hiden=3", "control.neural.hiden", "did you mean control.neural.hidden"),
    # values outside the physics: inf passes "> 0", nan fails every comparison
    ("drone.youngs_modulus=inf", "drone.youngs_modulus", "> 0 Pa"),
    ("drone.mass=inf", "drone.mass", "> 0 kg"),
    ("drone.mass=nan", "drone.mass", "> 0 kg"),
    ("drone.mass=-1", "drone.mass", "> 0 kg"),
    ("drone.max_thrust=inf", "drone.max_thrust", "> 0 N"),
    ("drone.poisson_ratio=nan", "drone.poisson_ratio", "in (0, 0.5)"),
    ("drone.damping=-inf", "drone.damping", ">= 0"),
    ("drone.rotor_radius=0", "drone.rotor_radius", "> 0 m"),
    ("drone.imu_radius=-0.1", "drone.imu_radius", "> 0 m"),
    ("drone.mesh.outline=exakt", "drone.mesh.outline", "resampled, or exact"),
    ("drone.mesh.outline=exact", "drone.mesh.outline", "with drone.mesh.layers >= 1"),   # the flower: fTetWild
    ("drone.mesh.envelope=0.5", "drone.mesh.envelope", "(relative to the bounding box diagonal) or null"),
    ("drone.size=[3.6,inf,3.6]", "drone.size", "positive lengths"),
    ("sim.gravity=nan", "sim.gravity", ">= 0"),
    ("sim.gravity=-9.81", "sim.gravity", ">= 0"),
    ("sim.max_speed=-1", "sim.max_speed", "> 0 m/s"),
    ("sim.max_stretch=0.5", "sim.max_stretch", "> 1"),
    ("sim.control_dt=inf", "sim.control_dt", "> 0 s"),
    ("sim.friction=-0.5", "sim.friction", ">= 0"),
    ("sim.ground=inf", "sim.ground", "finite"),
    ("control.kd=-1", "control.kd", ">= 0"),
    ("control.waypoint_max=0", "control.waypoint_max", "> 0 or null"),
    ("control.approach_speed=-1", "control.approach_speed", "> 0 m/s or null"),
    ("control.approach_speed=0.5", "control.approach_speed", "null while control.waypoint_max is null"),
    ("control.bend_snr=-1", "control.bend_snr", ">= 0"),
    ("control.q_s_alike=-1", "control.q_s_alike", ">= 0"),
    ("control.r_alike=-1", "control.r_alike", ">= 0"),
    ("control.share_pull=2", "control.share_pull", "in [0, 1]"),
    ("control.share_pull=0.2 control.feedforward=true", "control.share_pull", "feedforward"),
    ("control.integral=0", "control.integral", "in (0, 1]"),
    ("model.ensemble=0", "model.ensemble", "in [1, 32]"),
    ("control.lowpass=-0.01", "control.lowpass", "in [0, 1] s"),
    ("control.delay_phase_deg=0", "control.delay_phase_deg", "in (0, 180] deg"),
    ("control.delay_phase_deg=45", "control.delay_phase_deg", "null while model.command_delay is 0"),
    ("control.q_p_axes=[1,1]", "control.q_p_axes", "3 numbers > 0"),
    ("control.q_p_axes=[1,1,-2]", "control.q_p_axes", "one per axis"),
    ("control.q_e_axes=[1,1]", "control.q_e_axes", "one per Euler angle"),
    ("control.q_e=inf", "control.q_e", "> 0"),
    ("control.kp=nan", "control.kp", "in [0, 1]"),
    ("noise.delay=-0.01", "noise.delay", ">= 0"),
    ("model.lr=inf", "model.lr", "allowed > 0"),
    ("data.region=nan", "data.region", "> 0 m"),
    ("data.bend_budget_deg=0", "data.bend_budget_deg", "in (0, 180] deg, or null"),
    ("seed=-1", "seed", "0 to 4294967295"),
    ("seed=4294967296", "seed", "0 to 4294967295"),
    ("drone.mesh.edge_length=5", "drone.mesh.edge_length", "in [0.0435, 0.9] m"),
    ("drone.mesh.edge_length=0.001", "drone.mesh.edge_length", "at most about 300,000 elements"),
    ("drone=rod drone.mesh.edge_length=3", "drone.mesh.edge_length", "at least 4 elements"),
    ("drone.mesh.edge_length=inf", "drone.mesh.edge_length", "m for this flower"),
    ("sim.precision=float16", "sim.precision", "float64 or float32"),
    ("sim.mass_scaling=-0.01", "sim.mass_scaling", "in [0, 0.1]"),
    ("sim.mass_scaling=5", "sim.mass_scaling", "in [0, 0.1]"),
    ("experiment=bench_sim experiment.params.mass_scaling=0", "experiment.params.mass_scaling", "in (0, 0.1]"),
    ("drone.params.petal_width=inf", "drone.params.petal_width", "finite"),
    ("sim.obstacles=[{min:[1,2,3]}]", "sim.obstacles[0].max", "set it"),
    ("drone.mass=${nope}", "drone.mass", "nope"),
    # rotor and sensor counts against the paper's designs (supplement B)
    ("drone=rod drone.num_rotors=500", "drone.num_rotors", "allowed 5"),
    ("drone=elephant drone.num_rotors=7", "drone.num_rotors", "allowed 2"),
    ("drone=bunny drone.num_sensors=20", "drone.num_sensors", "allowed 0 to 3"),
    ("drone=rod drone.num_sensors=300", "drone.num_sensors", "allowed 0 to 8"),
    ("drone=flower drone.num_rotors=10", "drone.num_rotors", "allowed 9"),
    ("drone=donut drone.num_sensors=5", "drone.num_sensors", "allowed 0 to 4"),
    # effects: known names, known parameters (listed), physical ranges, finite numbers
    ("+sim.effects=[{name:rotor_drag,k:-0.1}]", "sim.effects[0] (rotor_drag)", "rotor_drag.k = -0.1 is out of range: allowed >= 0"),
    ("+sim.effects=[{name:rotor_drag,kk:0.1}]", "sim.effects[0].kk", "allowed k"),
    ("+sim.effects=[{name:thrust_loss,fractoin:0.1}]", "sim.effects[0].fractoin", "allowed rotor, fraction"),
    ("+sim.effects=[{name:rotor_dragg}]", "sim.effects[0].name", "rotor_drag"),
    ("+sim.effects=[{name:wind,velocity:[1,0,inf]}]", "sim.effects[0].velocity[2]", "finite"),
    ("+sim.effects=[{name:motor_lag,tau:-1}]", "motor_lag.tau", ">= 0 s"),
    ("+sim.effects=[{name:payload,mass:nan}]", "sim.effects[0].mass", "finite"),
    # experiment.params: a checked set of keys, types and ranges
    ("+experiment.params.secnds=3", "experiment.params.secnds", "did you mean experiment.params.seconds"),
    ("+experiment.params.drones=[rod]", "experiment.params.drones", "allowed animate, controllers, paraview, seconds, start, target"),
    ("experiment=record +experiment.params.flights=3", "experiment.params.flights", "allowed none"),
    ("experiment.params.seconds=-1", "experiment.params.seconds", "> 0"),
    ("experiment.params.seconds=abc", "experiment.params.seconds", "Float"),
    ("~experiment.params.seconds", "experiment.params.seconds", "does not support deletion"),
    ("experiment=bench_control experiment.params.samples=2.5", "experiment.params.samples", "Integer"),
    ("experiment=nsweep experiment.params.n_values=[0,1]", "experiment.params.n_values", "> 0 each"),
    ("experiment=bench_sim experiment.params.drones=[rod,nope]", "experiment.params.drones", "rod, star"),
    ("experiment=bench_sim experiment.params.scaling_drone=rodd", "experiment.params.scaling_drone", "flower"),
    ("experiment=validate_fem +experiment.params.beam.lenght=2", "experiment.params.beam.lenght", "length"),
    ("experiment=hover_deform experiment.params.ramp_seconds=inf", "experiment.params.ramp_seconds", "finite"),
    ("experiment.params.animate=[ours,nope]", "experiment.params.animate", "ours, rigid_lqr, geometry_lqr, neural"),
    ("experiment.params.animate=[rigid_lqr] experiment.params.controllers=[ours]", "experiment.params.animate",
     "'rigid_lqr' is not flown"),
    # a misspelled controller is named as itself, with the registry's names, before any data or training
    ("experiment.params.controllers=[our,rigid_lqr]", "controller 'our' is unknown",
     "choose from ours, rigid_lqr, geometry_lqr, neural"),
    ("experiment=fleet experiment.params.controllers=[ours,rigid]", "experiment.params.controllers",
     "choose from ours, rigid_lqr, geometry_lqr, neural"),
    ("experiment=fleet experiment.params.controllers=[neural]", "experiment.params.controllers",
     "allowed a non-empty list of ours, rigid_lqr, geometry_lqr"),
    ("experiment.params.animate=true", "experiment.params.animate", "not a ListConfig, list or tuple"),
    # the discrepancy bench: library effects by name, the two bench strengths, each once
    ("experiment=discrepancy_bench experiment.params.effects=[nosuch]", "experiment.params.effects: effect 'nosuch'",
     "choose from rotor_reaction_torque, rotor_drag"),
    ("experiment=discrepancy_bench experiment.params.levels=[2]", "experiment.params.levels = [2]",
     "allowed 0 (moderate) or 1 (strong)"),
    ("experiment=discrepancy_bench experiment.params.effects=[wind,wind]", "experiment.params.effects = ['wind', 'wind']",
     "allowed distinct effects"),
    # an effect written through the plugin protocol declares its ranges as the library's do
    ("+sim.effects=[{_target_:sdexp.discrepancy.bench_effects.ThrustCurve,a:2}]", "sim.effects[0] (thrust_curve)",
     "thrust_curve.a = 2 is out of range: allowed in [0, 1]"),
    ("experiment=obstacle experiment.params.animate=[ours]", "experiment.params.animate", "not a valid bool"),
])
def test_bad_config_values_name_the_key_and_the_allowed_values(override, key, allowed):
    message = rejected(*override.split())
    assert key in message and allowed in message, message


@pytest.mark.parametrize("experiment", conf.names("experiment"))
def test_every_experiment_declares_its_params(experiment):
    cfg = make_cfg(f"experiment={experiment}")
    preflight(cfg)
    typed(cfg)   # its own defaults pass its own checks
    assert list(cfg.experiment.params) == [f.name for f in __import__("dataclasses").fields(PARAMS[experiment])]
    assert sorted(cfg.experiment.params) == names(PARAMS[experiment])


# ------------------------------------------------------------------ the command line

def sdexp(*args, cwd):
    return subprocess.run([sys.executable, "-m", "sdexp.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "HYDRA_FULL_ERROR": ""})


def assert_one_line_error(res, *words):
    assert res.returncode == EXIT_USER_ERROR, res.stderr
    err = res.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1 and err.startswith("sdexp: error: "), err
    for w in words:
        assert w in err, err


@pytest.mark.parametrize("args, words", [
    (["drone.youngs_modulos=5000"], ["drone.youngs_modulos", "did you mean drone.youngs_modulus"]),
    (["+drone.youngs_modulos=5000"], ["drone.youngs_modulos", "did you mean drone.youngs_modulus"]),
    (["drone=nope"], ["drone=nope", "flower", "rod"]),
    (["drone.mass=["], ["drone.mass=["]),
    (["drone.mass=abc"], ["drone.mass", "Float"]),
    (["experiment=bench_sim", "experiment.params.drone=[rod]"], ["experiment.params.drone", "drones"]),
])
def test_hydra_config_errors_are_one_line_with_the_user_error_code(tmp_path, args, words):
    assert_one_line_error(sdexp(*args, cwd=tmp_path), *words)
    assert list(tmp_path.iterdir()) == []   # nothing written


def test_a_bad_value_exits_2_in_one_line_and_leaves_no_run_folder(tmp_path):
    assert_one_line_error(sdexp("drone.mass=inf", cwd=tmp_path), "drone.mass", "> 0 kg")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, words", [
    (["experiment.params.rescore=true"], ["experiment.params.rescore = true", "scenarios.csv does not exist",
                                          "allowed only in the folder of an earlier bench run"]),
    (["experiment.params.scenario_dir=afile"], ["experiment.params.scenario_dir = 'afile'", "is a file",
                                                "allowed a folder"]),
])
def test_the_discrepancy_bench_refuses_its_folders_in_one_line_before_writing(tmp_path, args, words):
    (tmp_path / "afile").write_text("not a folder")
    res = sdexp("experiment=discrepancy_bench", *args, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert_one_line_error(res, *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_a_misspelled_controller_stops_the_run_before_its_data(tmp_path):
    """sota generates data and trains its nets before the first flight: the names come first."""
    res = sdexp("experiment.params.controllers=[ours,rigid_lqx]", f"cache_dir={tmp_path / 'cache'}", cwd=tmp_path)
    assert_one_line_error(res, "experiment.params.controllers", "'rigid_lqx'", "ours, rigid_lqr, geometry_lqr, neural")
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_run_folder_is_one_line_and_exit_2(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    res = sdexp("drone=rod", f"hydra.run.dir={tmp_path}/file/run", cwd=tmp_path)
    assert_one_line_error(res, "output folder", "hydra.run.dir")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


# ------------------------------------------------------------------ run folders

def test_runs_started_in_the_same_second_get_different_folders(tmp_path):
    cmd = [sys.executable, "-m", "sdexp.cli", "--cfg", "all", "--resolve", "-p", "hydra.run.dir"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    dirs = [p.communicate()[0].strip() for p in procs]
    assert dirs[0].startswith("outputs/sota/flower/") and dirs[0] != dirs[1]
    assert [d.rsplit("_", 1)[1] for d in dirs] == [str(p.pid) for p in procs]


def _fake_finished_run(folder, cfg, metrics):
    from omegaconf import OmegaConf
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    (folder / "metrics.json").write_text(json.dumps(metrics))
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_a_finished_run_is_skipped_only_with_the_same_resolved_config(tmp_path):
    from sdexp.eval.run import run_experiment
    cfg = make_cfg("experiment=bench_sim", "drone=rod", "experiment.params.drones=[rod]")
    before = _fake_finished_run(tmp_path / "run", cfg, {"rod_realtime_factor": 1.5})
    # same config: the old metrics, nothing run (a real bench_sim would have written bench_sim.csv)
    assert run_experiment(cfg, tmp_path / "run") == {"rod_realtime_factor": 1.5}
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()} == before
    # another modulus: an error naming the key and both values, the folder untouched
    other = make_cfg("experiment=bench_sim", "drone=rod", "experiment.params.drones=[rod]",
                     "drone.youngs_modulus=3000")
    with pytest.raises(UserError, match=r"finished run with another config \(drone\.youngs_modulus: "
                                        r"6000\.0 there, 3000\.0 here\)"):
        run_experiment(other, tmp_path / "run")
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()} == before
    # neither an option added since (absent there, off here) nor the worker count is another config
    from sdexp.eval.run import config_differences
    saved = {"control": {"r": 10.0}, "experiment": {"params": {"workers": 1}}}
    assert config_differences(saved, {"control": {"r": 10.0, "delay_phase_deg": None},
                                      "experiment": {"params": {"workers": 2}}}) == []
    assert config_differences(saved, {"control": {"r": 10.0, "delay_phase_deg": 45.0}}) == [
        "control.delay_phase_deg: '<absent>' there, 45.0 here"]
    # an interrupted run (config.yaml, no metrics.json) resumes only with its own config
    (tmp_path / "run" / "metrics.json").unlink()
    with pytest.raises(UserError, match="unfinished run with another config"):
        run_experiment(other, tmp_path / "run")
    # a finished run without its config cannot be vouched for
    (tmp_path / "run" / "metrics.json").write_text("{}")
    (tmp_path / "run" / "config.yaml").unlink()
    with pytest.raises(UserError, match="without its config.yaml"):
        run_experiment(cfg, tmp_path / "run")


def test_a_folder_in_use_by_a_live_run_is_an_error_and_a_killed_runs_lock_is_taken_over(tmp_path):
    from sdexp.eval.run import RUN_LOCK, claim
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; from sdexp.eval.run "
         "import claim; claim(Path(sys.argv[1])); print('held', flush=True); time.sleep(60)", str(tmp_path)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserError, match=rf"in use by another run \(pid {holder.pid} "):
            claim(tmp_path)
    finally:
        holder.kill()
        holder.wait()
    lock = claim(tmp_path)   # kill -9 left its lock: a dead pid's lock is stale
    assert json.loads(lock.read_text())["pid"] == os.getpid() and lock.name == RUN_LOCK


def test_only_one_of_two_concurrent_claims_wins(tmp_path):
    from concurrent.futures import ProcessPoolExecutor
    with ProcessPoolExecutor(2) as pool:
        results = list(pool.map(_try_claim_and_hold, [str(tmp_path)] * 2))
    assert sorted(results) == ["error", "held"]


def _try_claim_and_hold(folder):
    import os
    import time
    from pathlib import Path
    from sdexp.eval.run import claim
    marks = Path(folder).parent / (Path(folder).name + "-tried")
    marks.mkdir(exist_ok=True)
    try:
        claim(Path(folder))
        result = "held"
    except UserError:
        result = "error"
    (marks / str(os.getpid())).touch()
    deadline = time.monotonic() + 30.0
    while result == "held" and len(list(marks.iterdir())) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)   # hold the claim until the other process has tried (a loaded machine starts it late)
    return result


def test_an_output_folder_that_is_a_file_is_a_user_error(tmp_path):
    from sdexp.eval.run import run_experiment
    (tmp_path / "run").write_text("")
    with pytest.raises(UserError, match="cannot write the run's output folder"):
        run_experiment(make_cfg("experiment=gallery", "experiment.params.drones=[rod]"), tmp_path / "run")


# ------------------------------------------------------------------ caches

@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "no_arrays"])
def test_a_damaged_cache_entry_is_rebuilt(tmp_path, damage, caplog):
    import numpy as np
    from sdexp.cache import cached_arrays
    made = []

    def make():
        made.append(1)
        return {"points": np.arange(12.0).reshape(4, 3), "elems": np.arange(4)[None]}

    first = cached_arrays(tmp_path, "mesh3d-test", make)
    path = tmp_path / "mesh3d-test.npz"
    raw = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(raw[: len(raw) // 2])
    elif damage == "garbage":
        path.write_bytes(raw[:40] + b"\0" * 64 + raw[104:])
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        np.savez(path)
    again = cached_arrays(tmp_path, "mesh3d-test", make)
    assert len(made) == 2 and all(np.array_equal(first[k], again[k]) for k in first)
    assert "damaged" in caplog.text and path.read_bytes() == raw   # stored whole again
    assert cached_arrays(tmp_path, "mesh3d-test", make) and len(made) == 2    # and read back


def test_a_damaged_mesh_is_remeshed_not_a_traceback(tmp_path):
    from sdexp.sim.drone import make_shape, mesh_shape
    cfg = make_cfg("drone=rod")
    shape = make_shape(cfg.drone)
    points, elems = mesh_shape(shape, cfg.drone.mesh, str(tmp_path))
    (entry,) = tmp_path.glob("mesh2d-*.npz")
    entry.write_bytes(entry.read_bytes()[:100])
    p2, e2 = mesh_shape(shape, cfg.drone.mesh, str(tmp_path))
    assert (p2 == points).all() and (e2 == elems).all()


def test_an_unwritable_cache_is_a_user_error(tmp_path):
    import numpy as np
    from sdexp.cache import cached_arrays
    (tmp_path / "file").write_text("")
    with pytest.raises(UserError, match="cache_dir .* cannot be written"):
        cached_arrays(tmp_path / "file" / "cache", "k", lambda: {"a": np.zeros(1)})


# ------------------------------------------------------------------ measured logs

def _logs(folder, rows=20, **meta_extra):
    import numpy as np
    from sdexp.discrepancy.logs import FORMAT, channel_names, write_flight, write_meta
    rng = np.random.default_rng(0)
    C = len(channel_names(2, 2))
    for i in range(2):
        write_flight(folder, f"flight_{i:03d}", 0.01 * np.arange(rows), rng.uniform(0, 3, (rows, 2)),
                     rng.normal(scale=0.1, size=(rows, C)), 2, 2)
    write_meta(folder, {"format": FORMAT, "version": 1, "drone": "rod", "dim": 2, "sample_rate": 100.0,
                        "num_rotors": 2, "num_sensors": 2, **meta_extra})


def _read(folder, **kw):
    from sdexp.discrepancy.logs import read_logs
    return read_logs(folder, "rod", 2, 2, 2, **kw)


def test_clean_logs_read(tmp_path):
    _logs(tmp_path)
    assert len(_read(tmp_path, max_thrust=10.0).flights) == 2


@pytest.mark.parametrize("column, row, value, allowed", [
    ("p_x", 5, 1e308, "|p_x| <= 10000 m"),
    ("u1", 3, 1e308, "|u1| <= 1000 N"),   # (no max_thrust given: the generic bound)
    ("u0", 7, -40.0, "|u0| <= 15 N"),      # 1.5 x drone.max_thrust
    ("s1", 2, 10.0, "|s1| <= 6.28319 rad"),
    ("p_dot_y", 9, -5e3, "|p_dot_y| <= 1000 m/s"),
    ("e_dot", 1, 1e200, "|e_dot| <= 1000 rad/s"),
    ("e", 4, 1e300, "|e| <= 1000 rad"),
    ("t", 0, -1e308, "|t| <= 1e+06 s"),
])
def test_implausible_readings_name_file_column_and_row(tmp_path, column, row, value, allowed):
    import pandas as pd
    _logs(tmp_path)
    path = tmp_path / "flight_001.csv"
    table = pd.read_csv(path)
    table.loc[row, column] = value
    table.to_csv(path, index=False)
    before = path.read_bytes()
    with pytest.raises(UserError) as info:
        _read(tmp_path, max_thrust=None if column == "u1" else 10.0)
    msg = str(info.value)
    assert "flight_001.csv" in msg and f"column {column!r}, data row {row + 1}:" in msg and allowed in msg, msg
    assert path.read_bytes() == before


@pytest.mark.parametrize("meta, words", [
    ({"sample_rate": "fast"}, ["sample_rate = 'fast'", "finite number"]),
    ({"sample_rate": float("inf")}, ["sample_rate = inf"]),
    ({"num_rotors": "two"}, ["num_rotors = 'two'", "whole number"]),
    ({"dim": 2.5}, ["dim = 2.5", "whole number"]),
])
def test_bad_meta_numbers_name_the_key(tmp_path, meta, words):
    _logs(tmp_path, **meta)
    with pytest.raises(UserError) as info:
        _read(tmp_path)
    assert "meta.json" in str(info.value) and all(w in str(info.value) for w in words), str(info.value)


def test_a_drone_override_that_no_benchmarked_drone_sees_is_an_error():
    """The README's old sweep: drone.* landed on the default flower while bench_sim ran the rod."""
    from sdexp.eval.run import check_overrides_reach
    args = ["experiment=bench_sim", "experiment.params.drones=[rod]", "drone.youngs_modulus=3000"]
    with pytest.raises(UserError, match=r"drone\.youngs_modulus=3000 changes drone flower.*add drone=rod"):
        check_overrides_reach(make_cfg(*args), args)
    check_overrides_reach(make_cfg(*args, "drone=rod"), [*args, "drone=rod"])   # reaches the rod


def test_an_unknown_design_param_is_an_error_before_anything_is_written(tmp_path):
    from sdexp.eval.run import run_experiment
    with pytest.raises(UserError, match="petal_widht"):
        run_experiment(make_cfg("experiment=gallery", "experiment.params.drones=[flower]",
                                "+drone.params.petal_widht=0.5"), tmp_path / "run")
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ a drone of one's own (drone.mesh.file)

@pytest.fixture
def box_stl(tmp_path):
    """A closed 2 x 0.2 x 1 m box in metres, and the same box with one triangle missing."""
    import meshio
    import numpy as np

    from tests.sim.test_meshfile import box, extruded, circle
    v, f = box()
    meshio.write(tmp_path / "box.stl", meshio.Mesh(v, [("triangle", f)]))
    meshio.write(tmp_path / "open.stl", meshio.Mesh(v, [("triangle", f[1:])]))
    (tmp_path / "junk.stl").write_bytes(b"\x00\x01 not a mesh")
    v, f = extruded([circle(1.5), circle(1.0, cw=True)], holes=[(0.0, 0.0)])
    meshio.write(tmp_path / "ring.stl", meshio.Mesh(v, [("triangle", f)]))
    np.savetxt(tmp_path / "square.txt", [[0, 0], [2, 0], [2, 1], [0, 1]])
    return tmp_path


ON_BOX = "drone.rotors=[[-0.8,0.1,0],[0.8,0.1,0],[0,0.1,0.4]]"
ON_RING = "drone.rotors=[[1.25,0.1,0],[-1.25,0.1,0],[0,0.1,1.25]]"


@pytest.mark.parametrize("overrides, words", [
    ("drone=custom", ["drone.mesh.file has no value"]),
    ("drone=custom drone.mesh.file=box.stl", ["drone.rotors lists 0", "at least 3 rotors"]),
    (f"drone=custom drone.mesh.file=none.stl {ON_BOX}", ["drone.mesh.file = 'none.stl': no such file", "STL, OBJ"]),
    (f"drone=custom drone.mesh.file=junk.stl {ON_BOX}", ["drone.mesh.file = junk.stl: cannot read it", "STL, OBJ"]),
    (f"drone=custom drone.mesh.file=open.stl {ON_BOX}", ["drone.mesh.file = open.stl: the surface is not closed"]),
    (f"drone=custom drone.mesh.file=box.stl drone.mesh.scale=1000 {ON_BOX}",
     ["drone.mesh.scale = 1000 makes the body of box.stl 2000 m across", "allowed 0.05 to 50 m"]),
    (f"drone=custom drone.mesh.file=box.stl drone.mesh.scale=0 {ON_BOX}", ["drone.mesh.scale", "> 0"]),
    (f"drone=custom drone.mesh.file=box.stl drone.mesh.edge_length=0.001 {ON_BOX}",
     ["drone.mesh.edge_length", "at most about 300,000 elements"]),
    (f"drone=custom drone.mesh.file=box.stl drone.mesh.layers=2 {ON_BOX}", ["drone.mesh.layers", "[] and 0"]),
    ("drone=custom drone.mesh.file=box.stl drone.rotors=[[-0.8,0.1,0],[0.8,0.1,0]]",
     ["drone.rotors lists 2", "at least 3 rotors"]),
    ("drone=custom drone.dim=2 drone.mesh.file=square.txt drone.rotors=[[1,1]]", ["drone.rotors lists 1", "at least 2"]),
    (f"drone=custom drone.mesh.file=box.stl drone.num_rotors=4 {ON_BOX}", ["drone.num_rotors = 4", "allowed 3"]),
    (f"drone=custom drone.mesh.file=box.stl {ON_BOX} drone.rotor_normals=[[0,1,0]]",
     ["drone.rotor_normals lists 1", "one per rotor (3)"]),
    ("drone=custom drone.mesh.file=box.stl drone.rotors=[[-0.8,0.1,0],[0.8,0.1,0],[0,0.1,3]]",
     ["drone.rotors[2] = [0.0, 0.1, 3.0] is off the body of box.stl", "within drone.rotor_radius"]),
    (f"drone=custom drone.mesh.file=ring.stl {ON_RING}", ["drone.num_sensors = 3", "frame IMU", "drone.imus"]),
    (f"drone=flower drone.mesh.file=box.stl {ON_BOX} drone.num_rotors=3",
     ["drone.size = [3.6, 0.225, 3.6]", "allowed [] for a drone from drone.mesh.file"]),
    ("drone=flower drone.rotors=[[0,0.1,0]]", ["drone.rotors", "[] unless drone.mesh.file is set"]),
])
def test_a_drone_from_a_bad_mesh_file_is_one_clear_error(box_stl, monkeypatch, overrides, words):
    monkeypatch.chdir(box_stl)   # relative files are read from the working directory
    message = rejected(*overrides.split())
    assert all(w in message for w in words), message


def test_a_missing_mesh_file_on_the_command_line_is_one_line_and_writes_nothing(tmp_path):
    res = sdexp("drone=custom", "drone.mesh.file=none.stl", ON_BOX, cwd=tmp_path)
    assert_one_line_error(res, "drone.mesh.file = 'none.stl': no such file", "STL, OBJ")
    assert list(tmp_path.iterdir()) == []
