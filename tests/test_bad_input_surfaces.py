"""Bad input on the surfaces beside the experiments (issue 26): the paper report, a sweep's report,
the launchers, a full disk, rejected runs. As in test_bad_input.py: every case is one line naming
the key, file or path and what is allowed, exit code 2, no traceback, and nothing left behind."""
import json
import os
import subprocess
import sys

import pytest
import yaml

from sdexp.errors import EXIT_USER_ERROR, UserError
from tests.test_bad_input import assert_one_line_error, sdexp


def run_main(main, argv, capsys):
    """A module's main() in this process: (exit code, stderr) as a shell would see them."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    return info.value.code, capsys.readouterr().err


def assert_one_line(code, err, *words):
    assert code == EXIT_USER_ERROR, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and err.startswith("sdexp: error: "), err
    for w in words:
        assert w in err, err


# ------------------------------------------------------------------ python -m sdexp.eval.paper_report

def _sota_run(folder, seed, error=0.1):
    folder.mkdir(parents=True)
    metrics = {}
    for name, ok, t, err in (("ours", True, 20.0, error), ("rigid_lqr", False, 0.3, 5.0)):
        metrics.update({f"{name}_survival_time": t, f"{name}_survived": ok, f"{name}_final_error": err})
    (folder / "metrics.json").write_text(json.dumps(metrics))
    (folder / "config.yaml").write_text(yaml.safe_dump(
        {"seed": seed, "sim": {"element": "quadratic", "threads": 1},
         "experiment": {"name": "sota", "params": {"start": [0, 0, 0], "target": [3, 3, 3], "seconds": 20.0}}},
        sort_keys=False))
    (folder / "sota.csv").write_text("controller,final_error\nours,0.1\nrigid_lqr,5.0\n")


@pytest.fixture
def results(tmp_path):
    """Three seeds of a complete SOTA result: 'reproduced', 3 of 3."""
    root = tmp_path / "results"
    _sota_run(root / "sota", 0)
    for seed in (1, 2):
        _sota_run(root / "sota_seeds" / f"seed{seed}", seed)
    return root


def _cut(path, keep):
    path.write_text(path.read_text()[:keep])


@pytest.mark.parametrize("damage, file, words", [
    (lambda f: _cut(f / "config.yaml", -4), "config.yaml", ["truncated"]),                 # a value cut mid-line
    (lambda f: _cut(f / "config.yaml", (f / "config.yaml").read_text().index("experiment:")), "config.yaml",
     ["truncated"]),                                                                          # the last section gone
    (lambda f: (f / "config.yaml").write_text("seed: [1\n"), "config.yaml", ["not valid YAML"]),
    (lambda f: (f / "config.yaml").unlink(), "config.yaml", ["is missing"]),
    (lambda f: (f / "config.yaml").write_text((f / "config.yaml").read_text().replace("name: sota", "name: nsweep")),
     "config.yaml", ["a run of nsweep, not of sota"]),
    (lambda f: (f / "metrics.json").unlink(), "metrics.json", ["is missing"]),
    (lambda f: _cut(f / "metrics.json", 40), "metrics.json", ["not valid JSON"]),
    (lambda f: (f / "metrics.json").write_text("[1, 2]"), "metrics.json", ["not a mapping"]),
    (lambda f: (f / "metrics.json").write_text(json.dumps(
        {k: v for k, v in json.loads((f / "metrics.json").read_text()).items() if k != "ours_final_error"})),
     "metrics.json", ["has no ours_final_error"]),
    (lambda f: _cut(f / "sota.csv", -3), "sota.csv", ["truncated"]),
    (lambda f: (f / "sota.csv").write_text("controller,final_error\nours,0.1\nrigid_lqr\n"), "sota.csv",
     ["line 3 has 1 fields, its header 2"]),
    (lambda f: (f / "sota.csv").write_text(""), "sota.csv", ["empty"]),
])
def test_the_paper_report_refuses_a_damaged_run_naming_the_file(results, capsys, damage, file, words):
    from sdexp.eval.paper_report import main
    damage(results / "sota_seeds" / "seed2")
    code, err = run_main(main, [str(results)], capsys)
    assert_one_line(code, err, str(results / "sota_seeds" / "seed2" / file), *words)
    assert not (results / "REPORT.md").exists() and not list(results.glob(".*tmp"))   # nothing written


def test_a_seed_folder_without_its_files_is_refused_not_a_smaller_count(results, capsys):
    from sdexp.eval.paper_report import main
    (results / "sota_seeds" / "seed3").mkdir()   # a job that never finished, committed by mistake
    code, err = run_main(main, [str(results)], capsys)
    assert_one_line(code, err, "seed3/metrics.json is missing")


def test_the_paper_report_lists_the_runs_it_leaves_out(results, capsys):
    from sdexp.eval.paper_report import main, render
    assert "3 of 3" in render(results) and "Left out" not in render(results)
    config = results / "sota_seeds" / "seed2" / "config.yaml"
    config.write_text(config.read_text().replace("element: quadratic", "element: linear"))
    text = render(results)
    assert "survived 2 of 2" in text and "Left out (not on the quadratic simulator): `sota_seeds/seed2`" in text
    main([str(results)])
    assert (results / "REPORT.md").read_text() == text


@pytest.mark.parametrize("make, words", [
    (lambda p: None, ["does not exist"]),
    (lambda p: p.write_text("not a folder"), ["is not a folder"]),
])
def test_the_paper_report_on_a_missing_folder_or_a_file_is_one_line(tmp_path, make, words):
    make(tmp_path / "results")
    res = subprocess.run([sys.executable, "-m", "sdexp.eval.paper_report", str(tmp_path / "results")],
                         capture_output=True, text=True, cwd=tmp_path)
    assert_one_line(res.returncode, res.stderr, str(tmp_path / "results"), *words)


# ------------------------------------------------------------------ sdexp experiment=report

def _job(folder, seed, finished=True):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(yaml.safe_dump({"seed": seed, "experiment": {"name": "sota"}}))
    if finished:
        (folder / "metrics.json").write_text(json.dumps({"ours_final_error": 0.1 * seed}))


@pytest.mark.parametrize("unfinished, words", [
    (lambda s: _job(s / "seed=2", 2, finished=False), ["1 unfinished job", "seed=2", "remove its folder"]),
    (lambda s: (s / "seed=2").mkdir() or (s / "seed=2" / "cli.log").write_text("started\n"),
     ["1 unfinished job", "seed=2"]),                                 # killed before its config was written
    (lambda s: [_job(s / f"seed={i}", i, finished=False) for i in (2, 3)], ["2 unfinished jobs", "seed=2, seed=3"]),
])
def test_a_sweep_with_an_unfinished_job_names_it(tmp_path, unfinished, words):
    from sdexp.eval.stats import find_jobs
    sweep = tmp_path / "sweep"
    for seed in (0, 1):
        _job(sweep / f"seed={seed}", seed)
    unfinished(sweep)
    with pytest.raises(UserError) as info:
        find_jobs(sweep)
    assert all(w in str(info.value) for w in [str(sweep), *words]), str(info.value)


def test_the_report_command_on_a_sweep_with_an_unfinished_job_is_one_line(tmp_path):
    sweep = tmp_path / "sweep"
    _job(sweep / "seed=0", 0)
    _job(sweep / "seed=1", 1, finished=False)
    res = sdexp("experiment=report", f"sweep_dir={sweep}", f"hydra.run.dir={tmp_path / 'report'}", cwd=tmp_path)
    assert_one_line_error(res, "1 unfinished job", "seed=1", "no metrics.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep"]


# ------------------------------------------------------------------ sweep launchers

def _launcher(*overrides):
    from tests.conftest import make_cfg
    return make_cfg(*overrides, hydra=True).hydra.launcher


@pytest.mark.parametrize("overrides, words", [
    (["hydra/launcher=joblib", "hydra.launcher.n_jobs=0"], ["hydra.launcher.n_jobs = 0", "a number of jobs >= 1, or -1 to -2"]),
    (["hydra/launcher=joblib", "hydra.launcher.n_jobs=-5"], ["hydra.launcher.n_jobs = -5", "-1 to -2"]),
    (["hydra/launcher=joblib", "hydra.launcher.timeout=-3"], ["hydra.launcher.timeout = -3.0", "> 0 seconds"]),
    (["hydra/launcher=joblib", "hydra.launcher.batch_size=0"], ["hydra.launcher.batch_size = '0'", "'auto' or a whole number"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.tasks_per_node=0"], ["hydra.launcher.tasks_per_node = 0", ">= 1"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=-1"], ["hydra.launcher.timeout_min = -1", "> 0 minutes"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=0"], ["hydra.launcher.timeout_min = 0", "> 0 minutes"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.nodes=0"], ["hydra.launcher.nodes = 0", ">= 1"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.cpus_per_task=0"], ["hydra.launcher.cpus_per_task = 0", ">= 1"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.gpus_per_node=-1"], ["hydra.launcher.gpus_per_node = -1", ">= 0"]),
    (["hydra/launcher=submitit_slurm", "hydra.launcher.mem_gb=0"], ["hydra.launcher.mem_gb = 0", ">= 1"]),
])
def test_launcher_settings_are_checked_before_the_sweep(monkeypatch, overrides, words):
    from sdexp import launchers, parallel
    monkeypatch.setattr(parallel, "available_cores", lambda: 2)
    with pytest.raises(UserError) as info:
        launchers.check_launcher(_launcher(*overrides))
    assert all(w in str(info.value) for w in words), str(info.value)


def test_good_launcher_settings_pass(monkeypatch):
    from sdexp import launchers, parallel
    monkeypatch.setattr(parallel, "available_cores", lambda: 2)
    for overrides in (["hydra/launcher=joblib"], ["hydra/launcher=joblib", "hydra.launcher.n_jobs=-2"],
                      ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10"], []):
        launchers.check_launcher(_launcher(*overrides))


@pytest.mark.parametrize("args, words", [
    (["hydra/launcher=joblib", "hydra.launcher.n_jobs=0"], ["hydra.launcher.n_jobs = 0", "(-1: all"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.tasks_per_node=0"], ["hydra.launcher.tasks_per_node = 0"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=-1"], ["hydra.launcher.timeout_min = -1"]),
    (["hydra/launcher=submitit_slurm"], ["submitit_slurm needs Slurm", "sbatch and srun not found", "joblib"]),
    (["hydra/launcher=joblib", "hydra.launcher.njobs=2"],
     ["hydra.launcher.njobs is not a key of hydra.launcher (hydra/launcher=joblib)",
      "did you mean hydra.launcher.n_jobs?", "allowed _target_, backend"]),
    (["hydra.launcher.njobs=2"], ["hydra.launcher.njobs", "the basic launcher", "hydra/launcher=joblib"]),
    (["hydra/launcher=submitit_local", "hydra.launcher.timeout=3"], ["did you mean hydra.launcher.timeout_min?"]),
])
def test_a_bad_launcher_setting_stops_the_sweep_before_any_job(tmp_path, args, words):
    env = {**os.environ, "HYDRA_FULL_ERROR": "", "PATH": os.path.dirname(sys.executable)}   # no Slurm here
    res = subprocess.run([sys.executable, "-m", "sdexp.cli", "-m", "experiment=gallery", "seed=0,1", *args],
                         capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert_one_line_error(res, *words)
    assert list(tmp_path.iterdir()) == []   # no sweep folder, no job folder


# ------------------------------------------------------------------ rejected runs leave nothing

def reject_after_writing(run):
    """A runner that writes part of its output and then finds bad input (as the discrepancy
    workflow does with its logs)."""
    import pandas as pd
    run.table(pd.DataFrame({"a": [1.0]}), "partial")
    (run.out_dir / "frames_vtu").mkdir()
    raise UserError("discrepancy.measured = 'nope' is not a folder")


def fill_the_disk(run):
    """A runner whose table meets a full disk."""
    import errno
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(run.out_dir / "sota.csv"))


def _cfg(*overrides):
    from tests.conftest import make_cfg
    return make_cfg("experiment=gallery", "experiment.params.drones=[rod]", *overrides)


@pytest.mark.parametrize("runner, words", [
    ("reject_after_writing", ["discrepancy.measured = 'nope' is not a folder"]),
    ("fill_the_disk", ["sota.csv", "No space left on device", "MB free there", "hydra.run.dir=<folder>"]),
])
def test_a_rejected_run_leaves_nothing_that_blocks_its_corrected_rerun(tmp_path, cache_dir, runner, words):
    from sdexp.eval.run import run_experiment
    bad = _cfg(f"experiment._target_=tests.test_bad_input_surfaces.{runner}")
    with pytest.raises(UserError) as info:
        run_experiment(bad, tmp_path / "run")
    assert all(w in str(info.value) for w in words), str(info.value)
    assert list((tmp_path / "run").iterdir()) == []   # no config.yaml, overrides.yaml, partial table
    metrics = run_experiment(_cfg(), tmp_path / "run")   # the corrected command, same folder
    assert metrics["rod_elements"] > 0 and (tmp_path / "run" / "metrics.json").exists()


def test_a_rejected_resumed_run_keeps_the_earlier_runs_files(tmp_path):
    from omegaconf import OmegaConf
    from sdexp.eval.run import run_experiment
    bad = _cfg("experiment._target_=tests.test_bad_input_surfaces.reject_after_writing")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text(OmegaConf.to_yaml(bad, resolve=True))   # killed earlier
    with pytest.raises(UserError):
        run_experiment(bad, tmp_path / "run")
    assert (tmp_path / "run" / "config.yaml").exists()


def test_a_run_rejected_inside_its_runner_leaves_no_folder_on_the_command_line(tmp_path, cache_dir):
    res = sdexp("experiment=gallery", "experiment.params.drones=[rod]",
                "experiment._target_=tests.test_bad_input_surfaces.reject_after_writing",
                f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert_one_line_error(res, "discrepancy.measured = 'nope' is not a folder")
    assert list(tmp_path.iterdir()) == []   # no cli.log, config.yaml, overrides.yaml


# ------------------------------------------------------------------ a full disk

def _enospc(*args, **kwargs):
    import errno
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _half_then_full(path_arg=0):
    """A write that puts half a file down, then finds the disk full."""
    def write(*args, **kwargs):
        target = args[path_arg]
        if hasattr(target, "write"):
            target.write(b"half a file")
        else:
            open(target, "wb").write(b"half a file")
        _enospc()
    return write


def test_a_full_disk_while_writing_a_cache_entry_names_the_cache(tmp_path, monkeypatch):
    import numpy as np
    from sdexp.cache import cached_arrays
    monkeypatch.setattr(np, "savez", _half_then_full())
    with pytest.raises(UserError) as info:
        cached_arrays(tmp_path / "cache", "mesh3d-x", lambda: {"a": np.zeros(3)})
    msg = str(info.value)
    assert str(tmp_path / "cache" / "mesh3d-x.npz") in msg and "No space left" in msg and "cache_dir=<folder>" in msg, msg
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [".locks"]   # no entry, no temporary file


def test_a_full_disk_while_writing_a_data_chunk_leaves_no_half_chunk(tmp_path, monkeypatch):
    import numpy as np
    from sdexp.model import dataset
    monkeypatch.setattr(np, "savez", _half_then_full())
    path = tmp_path / "data-x" / "chunk-00002.npz"
    with pytest.raises(OSError) as info:
        dataset._write_npz(path, {"a": np.zeros(3)}, {"samples": 3})
    assert info.value.filename == str(path) and list(path.parent.iterdir()) == []


def test_a_full_cache_disk_in_a_run_names_the_cache(tmp_path, cache_dir, monkeypatch):
    import errno
    from sdexp.eval.run import run_experiment
    from sdexp.eval import gallery

    def full(run):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.path.join(cache_dir, "data-x", "chunk-00001.npz"))
    monkeypatch.setattr(gallery, "run", full)
    with pytest.raises(UserError) as info:
        run_experiment(_cfg(), tmp_path / "run")
    assert "chunk-00001.npz" in str(info.value) and "cache_dir=<folder> or SDEXP_CACHE" in str(info.value)
    assert list((tmp_path / "run").iterdir()) == []


def test_a_full_disk_while_writing_a_table_leaves_no_half_table(tmp_path, monkeypatch):
    import pandas as pd
    from sdexp.eval.run import Run
    monkeypatch.setattr(pd.DataFrame, "to_csv", lambda self, path, **kw: _half_then_full()(path))
    with pytest.raises(OSError) as info:
        Run(None, tmp_path).table(pd.DataFrame({"a": [1]}), "sota")
    assert info.value.filename == str(tmp_path / "sota.csv") and list(tmp_path.iterdir()) == []


class _Recorder:
    def __init__(self, frames, times):
        self.points, self.times, self.frame_rate = list(frames), list(times), 25.0


def _flight_pictures(tmp_path, paraview=True):
    """save_flight on a tiny 2D rod flight: (the run folder's files, the result)."""
    import numpy as np
    from types import SimpleNamespace
    from sdexp.eval.animation import save_flight
    rest = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.2], [0.0, 0.2]])
    frames = [rest + [0.01 * i, 0.0] for i in range(6)]
    drone = SimpleNamespace(boundary=np.array([[0, 1], [1, 2], [2, 3], [3, 0]]),
                            fem=SimpleNamespace(rest=rest, mass=np.ones(4), elems=np.array([[0, 1, 2], [0, 2, 3]])))
    out = save_flight(tmp_path, "flight", _Recorder(frames, 0.04 * np.arange(6)), drone, progress=False, paraview=paraview)
    return sorted(p.name for p in tmp_path.iterdir()), out


def _meshio_fails_at(frame, error):
    import meshio
    real = meshio.write

    def write(path, mesh, **kw):
        if str(path).endswith(f"_{frame:05d}.vtu"):
            open(path, "wb").close()   # the 0-byte frame a full disk leaves
            raise error
        return real(path, mesh, **kw)
    return write


def test_a_full_disk_during_the_paraview_series_is_one_error_and_no_partial_series(tmp_path, monkeypatch):
    import errno
    import meshio
    monkeypatch.setattr(meshio, "write", _meshio_fails_at(3, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))))
    with pytest.raises(UserError) as info:
        _flight_pictures(tmp_path)
    assert str(tmp_path / "flight_vtu" / "flight_00003.vtu") in str(info.value) and "No space left" in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flight.mp4"]   # the video is whole; no series, no temp folder


def test_a_paraview_series_that_cannot_be_written_names_the_file_and_keeps_the_video(tmp_path, monkeypatch, caplog):
    import meshio
    monkeypatch.setattr(meshio, "write", _meshio_fails_at(2, PermissionError(13, "Permission denied")))
    files, out = _flight_pictures(tmp_path)
    assert files == ["flight.mp4"] and list(out) == ["video"]
    warning = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(f"the ParaView series {tmp_path / 'flight_vtu' / 'flight_00002.vtu'} could not be written" in w
               for w in warning), warning
    assert not any("animation" in w for w in warning)


def test_a_full_disk_during_the_video_leaves_no_partial_video(tmp_path, monkeypatch):
    from sdexp.eval import animation
    calls = []

    def add(self, frame):
        calls.append(1)
        if len(calls) == 3:
            _enospc()
    monkeypatch.setattr(animation._Sink, "add", add)
    with pytest.raises(UserError) as info:
        _flight_pictures(tmp_path, paraview=False)
    assert str(tmp_path / "flight.mp4") in str(info.value) and "No space left" in str(info.value)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ vague messages made exact

def test_a_meta_sample_rate_that_contradicts_the_data_blames_meta_json(tmp_path):
    from tests.test_bad_input import _logs, _read
    _logs(tmp_path, sample_rate=50.0)   # the flights are spaced 0.01 s: 100 Hz
    with pytest.raises(UserError) as info:
        _read(tmp_path)
    msg = str(info.value)
    assert msg.startswith(f"{tmp_path / 'meta.json'}: sample_rate = 50.0 Hz contradicts the flights") and \
        "spaced 0.01 s (100 Hz)" in msg and "set sample_rate to 100" in msg, msg


def test_an_unevenly_spaced_flight_still_blames_its_time_column(tmp_path):
    import pandas as pd
    from tests.test_bad_input import _logs, _read
    _logs(tmp_path)
    path = tmp_path / "flight_001.csv"
    table = pd.read_csv(path)
    table.loc[5:, "t"] += 0.005
    table.to_csv(path, index=False)
    with pytest.raises(UserError, match=r"flight_001.csv: column 't' is not spaced 1/sample_rate = 0.01 s \(data row 6\)"):
        _read(tmp_path)


class _BlowingUp:
    """A simulator that diverges on its 30th step (the bench resets it and goes on)."""
    n_sub, dt, t, reduced = 4, 0.0025, 0.0, None

    def __init__(self, *args):
        self.steps, self.alive = 0, True
        self.failure = type("F", (), {"reason": "blow-up"})()

    def step(self, u):
        self.steps += 1
        self.alive = self.steps != 30

    def reset(self):
        self.alive = True


def test_a_benchmark_that_blows_up_reports_no_speed_anywhere(tmp_path, monkeypatch):
    from types import SimpleNamespace
    import pandas as pd
    from sdexp.eval import bench_sim
    from sdexp.eval.plots import bench_plot
    monkeypatch.setattr(bench_sim, "Simulator", _BlowingUp)
    drone = SimpleNamespace(num_rotors=2, max_thrust=1.0, dim=2, fem=SimpleNamespace(n_elems=10, order=2, rest=[0] * 8))
    drone_cfg = SimpleNamespace(name="rod", mesh=SimpleNamespace(edge_length=0.1))
    cfg = SimpleNamespace(sim=SimpleNamespace(control_dt=0.01, model="full"), noise=None)
    row = bench_sim.time_drone(drone, drone_cfg, cfg, seconds=0.5, seed=0)
    assert row["blowups"] == 1 and all(row[k] is None for k in bench_sim.SPEED), row
    rows = [{"series": "drone", **row, "bend_error": 0.01, "compliance_error": 0.02}]
    metrics = bench_sim.metrics(rows)
    assert metrics["rod_quadratic_realtime_factor"] is None and metrics["rod_quadratic_element_substeps_per_s"] is None
    assert metrics["rod_quadratic_blowups"] == 1
    table = pd.DataFrame(rows + [{**rows[0], "series": "scaling"}])
    for c in bench_sim.SPEED:
        table[c] = pd.to_numeric(table[c])
    bench_plot(table, tmp_path / "bench_sim.png")   # the plot draws no speed for it, and no error
    assert (tmp_path / "bench_sim.png").stat().st_size > 0
    monkeypatch.setattr(_BlowingUp, "step", lambda self, u: None)   # and one that does not blow up has its speed
    assert bench_sim.time_drone(drone, drone_cfg, cfg, seconds=0.5, seed=0)["realtime_factor"] > 0


@pytest.mark.parametrize("args, words", [
    (["experiment=validate_fem", "experiment.params.beam.lenght=2"],
     ["experiment.params.beam.lenght is not a parameter of validate_fem's beam",
      "did you mean experiment.params.beam.length?", "allowed length, poisson_ratio, sag, thickness, width, youngs_modulus"]),
    (["experiment=validate_fem", "experiment.params.bem.length=2"],
     ["experiment.params.bem.length is not a parameter of validate_fem", "did you mean experiment.params.beam?"]),
    (["experiment=bench_sim", "experiment.params.resolution_factors.x=2"],
     ["experiment.params.resolution_factors.x=2: experiment.params.resolution_factors is a list",
      "experiment.params.resolution_factors.0=", "[...]"]),
    (["drone.size.x=2"], ["drone.size.x=2: drone.size is a list"]),
])
def test_nested_and_list_keys_name_their_own_parent(tmp_path, args, words):
    assert_one_line_error(sdexp(*args, cwd=tmp_path), *words)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ a killed sweep

def held_job(run):
    """A sweep job that says it started (its pid) and waits while the test's hold file exists."""
    import time
    from pathlib import Path
    marks = Path(os.environ["SDEXP_TEST_MARKS"])
    (marks / str(os.getpid())).write_text(str(run.cfg.seed))
    while (marks / "hold").exists():
        time.sleep(0.1)
    return {"seed": run.cfg.seed}


def _descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in os.listdir(f"/proc/{p}/task") if os.path.exists(f"/proc/{p}/task") else []:
            try:
                kids = open(f"/proc/{p}/task/{task}/children").read().split()
            except OSError:
                continue
            for k in map(int, kids):
                if k not in out:
                    out.add(k)
                    todo.append(k)
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="reads the process tree from /proc")
def test_killing_a_joblib_sweep_takes_its_workers_down_and_the_rerun_resumes(tmp_path):
    import signal
    import time
    marks = tmp_path / "marks"
    marks.mkdir()
    (marks / "hold").touch()
    env = {**os.environ, "HYDRA_FULL_ERROR": "", "SDEXP_TEST_MARKS": str(marks)}
    cmd = [sys.executable, "-m", "sdexp.cli", "-m", "experiment=gallery", "seed=0,1",
           "experiment._target_=tests.test_bad_input_surfaces.held_job", "hydra/launcher=joblib",
           "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path / 'sweep'}"]
    parent = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300   # a loaded machine starts loky's workers late
        while len([m for m in marks.iterdir() if m.name != "hold"]) < 2:
            assert parent.poll() is None and time.monotonic() < deadline, parent.stderr.read().decode()[-2000:]
            time.sleep(0.2)
        family = _descendants(parent.pid)   # loky's workers and resource tracker
        workers = {int(m.name) for m in marks.iterdir() if m.name != "hold"}
        assert workers <= family
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in family) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = [p for p in family if _alive(p)]
        for p in left:
            os.kill(p, signal.SIGKILL)
        assert not left, f"{len(left)} of the killed sweep's processes outlived it by 10 s"
    finally:
        if parent.poll() is None:
            parent.kill()
    (marks / "hold").unlink()
    res = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    jobs = sorted(p for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert [json.loads((j / "metrics.json").read_text())["seed"] for j in jobs] == [0, 1]


# ------------------------------------------------------------------ the discrepancy workflow with few flights

@pytest.mark.parametrize("flights, holdout, floor, need", [
    (3, 0.5, 2, "it needs 4 measured flights at discrepancy.holdout = 0.5"),   # one flight to train on
    (3, 0.5, 8, "it needs 4 measured flights"),
    (4, 0.5, 2, "discrepancy.floor_flights >= 3"),                               # enough flights, too few floor ones
    (5, 0.2, 8, "it needs 8 measured flights at discrepancy.holdout = 0.2"),    # 1 held out
    (2, 0.5, 8, "it needs 4 measured flights"),
])
def test_too_few_flights_for_the_naming_test_say_how_many_it_needs(flights, holdout, floor, need):
    from sdexp.discrepancy.workflow import naming_shortfall
    msg = naming_shortfall(flights, holdout, floor)
    assert msg is not None and need in msg and f"{flights} measured flights" in msg and "not named" in msg, msg


@pytest.mark.parametrize("flights, holdout, floor", [(4, 0.5, 3), (8, 0.5, 8), (6, 0.5, 3)])
def test_enough_flights_name_as_before(flights, holdout, floor):
    from sdexp.discrepancy.workflow import naming_shortfall
    assert naming_shortfall(flights, holdout, floor) is None


def test_the_workflow_names_nothing_from_too_few_flights(tmp_path, cache_dir):
    """3 flights and 2 floor flights (the issue's case): even a payload that is there, and that
    the fit finds, is reported as not significant rather than named and added."""
    from dataclasses import replace
    from sdexp.discrepancy.workflow import run_workflow
    from sdexp.sim.drone import build_drone
    from tests.discrepancy.conftest import SMALL
    from tests.discrepancy.test_workflow import record
    from tests.conftest import make_config
    cfg = make_config(*SMALL, "experiment=discrepancy", f"cache_dir={cache_dir}")
    d = cfg.discrepancy
    cfg = replace(cfg, discrepancy=replace(d, candidates=["payload"], floor_flights=2,
                                           record=replace(d.record, flights=3)))
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    record(cfg, drone, tmp_path / "logs", [{"name": "payload", "mass": 0.3, "point": [0.6, 0.0, 0.8]}], seed=12)
    said = []
    rep = run_workflow(drone, cfg.drone, cfg.sim, cfg.noise, cfg.discrepancy, tmp_path / "logs", tmp_path / "out",
                       cfg.cache_dir, plots=False, log=said.append)
    assert rep["effects"] == [] and rep["verdict"] in ("none", "unexplained"), rep["verdict"]
    assert [e["name"] for e in rep["not_significant"]] == ["payload"], rep["rounds"]
    assert rep["too_few_flights"] and "it needs 4 measured flights" in rep["too_few_flights"]
    assert any("it needs 4 measured flights" in s for s in said)
    fitted = yaml.safe_load((tmp_path / "out" / "sim_fitted.yaml").read_text())
    assert fitted["effects"] == []   # nothing added to the simulator


def test_a_full_disk_while_saving_a_figure_leaves_no_half_picture(tmp_path, monkeypatch):
    from matplotlib.figure import Figure
    from sdexp.figures import save_figure
    fig = Figure()
    fig.add_subplot().plot([0, 1], [1, 0])
    monkeypatch.setattr(Figure, "savefig", lambda self, path, **kw: _half_then_full()(path))
    with pytest.raises(OSError) as info:
        save_figure(fig, tmp_path / "stats.png")
    assert info.value.filename == str(tmp_path / "stats.png") and list(tmp_path.iterdir()) == []
