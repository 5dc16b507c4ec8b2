"""Configs compose, experiments run shrunk, and bad input gets a clear error, not a traceback."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError

from sdexp.errors import UserError
from sdexp import conf
from sdexp.eval.run import preflight, run_experiment, typed
from sdexp.sim.drone import drone_names
from tests.conftest import make_cfg, make_config

EXPERIMENTS = conf.names("experiment")

DRONES = ["bunny", "diamond", "donut", "elephant", "engine", "flower", "leaf", "octopus",
          "orange_peel", "rainbow", "rod", "star"]


def test_the_twelve_paper_drones_are_configured():
    assert drone_names() == DRONES


@pytest.mark.parametrize("drone", DRONES)
def test_every_drone_config_is_valid_against_the_table(drone):
    cfg = make_cfg(f"drone={drone}")
    preflight(cfg)
    assert cfg.drone.mass == 1.0 and cfg.drone.max_thrust == 10.0
    table = {  # supplement B: modulus, bounding lengths, sensors, rotors
        "donut": (1e4, [3.5, 0.36, 3.5], 4, 4), "star": (3e3, [3.6, 0.375, 3.6], 4, 5),
        "flower": (6e3, [3.6, 0.225, 3.6], 8, 9), "leaf": (3e3, [2.4, 0.075, 4.5], 4, 4),
        "octopus": (1e4, [3.6, 1.5, 3.6], 8, 9), "orange_peel": (5e2, [3.0, 1.3, 2.9], 5, 5),
        "engine": (6e3, [1.90, 2.16], 6, 6), "bunny": (6e3, [1.12, 1.75], 3, 3),
        "diamond": (6e3, [1.47, 1.42], 8, 4), "elephant": (6e3, [2.46, 1.69], 3, 2),
        "rainbow": (6e3, [2.08, 1.30], 4, 2), "rod": (6e3, [8.0, 0.1], 8, 5),
    }
    E, size, sensors, rotors = table[drone]
    assert cfg.drone.youngs_modulus == E
    # the rod is read as a horizontal 8 m beam (the table lists it as 0.1 x 8.0)
    assert sorted(cfg.drone.size) == sorted(size)
    assert (cfg.drone.num_sensors, cfg.drone.num_rotors) == (sensors, rotors)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(experiment):
    cfg = make_cfg(f"experiment={experiment}")
    assert cfg.experiment.name == experiment
    preflight(cfg)
    config = typed(cfg)   # its params: its dataclass, the defaults in range
    assert type(config.experiment.params).__name__.lower() == experiment.replace("_", "") + "params"


def test_misspelled_key_is_an_error():
    with pytest.raises(ConfigKeyError):
        OmegaConf.merge(make_cfg(), OmegaConf.create({"drone": {"youngs_modulos": 5}}))


@pytest.mark.parametrize("override, key", [
    ("drone.youngs_modulus=-1", "drone.youngs_modulus"),
    ("drone.poisson_ratio=0.5", "drone.poisson_ratio"),
    ("drone.mass=0", "drone.mass"),
    ("sim.substep=0.5", "sim.substep"),
    ("drone.deformation_damping=-1", "drone.deformation_damping"),
    ("model.horizon=0", "model.horizon"),
    ("model.linear=[d,q]", "model.linear"),
    ("data.hover=bent", "data.hover"),
    ("data.around_hover=false data.hover=shape", "data.hover"),
    ("drone=rod drone.mesh.mirror=[x]", "drone.mesh.mirror"),
    ("drone.mesh.mirror=[y]", "drone.mesh.mirror"),
])
def test_non_physical_values_name_the_key(override, key):
    with pytest.raises(UserError, match=key.replace(".", r"\.")):
        preflight(make_cfg(*override.split()))


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "sdexp.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_cli_help_and_cfg_work_from_any_directory(tmp_path):
    res = _cli("--help", cwd=tmp_path)
    assert res.returncode == 0 and "drone: " in res.stdout and "experiment: " in res.stdout
    listed = res.stdout.split("Config groups")[0]   # the one-line-each part, above Hydra's group list
    missing = [n for n in [*EXPERIMENTS, *drone_names()] if f" {n} " not in listed.replace("\n", " \n")]
    assert not missing, f"sdexp --help does not describe {missing}: conf/hydra/help/sdexp.yaml"
    res = _cli("drone=rod", "--cfg", "job", cwd=tmp_path)
    assert res.returncode == 0 and "youngs_modulus: 6000" in res.stdout
    res = _cli("drone.youngs_modulos=5", "--cfg", "job", cwd=tmp_path)
    assert res.returncode != 0 and "youngs_modulos" in res.stderr


def test_cli_errors_are_short_and_list_choices(tmp_path):
    res = _cli("drone=nope", cwd=tmp_path)
    assert res.returncode != 0 and "flower" in res.stderr and "rod" in res.stderr
    res = _cli("experiment=nope", cwd=tmp_path)
    assert res.returncode != 0 and "bench_sim" in res.stderr
    res = _cli("experiment=bench_sim", "drone.poisson_ratio=0.7", f"hydra.run.dir={tmp_path}/o", cwd=tmp_path)
    assert res.returncode == 2
    assert "drone.poisson_ratio" in res.stderr and "Traceback" not in res.stderr
    res = _cli("experiment=bench_sim", "drone=bunny", "drone.num_rotors=5", "experiment.params.drones=[bunny]",
               f"hydra.run.dir={tmp_path}/o2", cwd=tmp_path)
    assert res.returncode == 2 and "num_rotors" in res.stderr and "Traceback" not in res.stderr


def test_bench_sim_runs_shrunk_and_resumes(tmp_path, cache_dir):
    cfg = make_cfg("experiment=bench_sim", "drone=rod", "experiment.params.drones=[rod]",
                   "experiment.params.seconds=0.05", "experiment.params.scaling_drone=rod",
                   "experiment.params.scaling_edges={linear: [], quadratic: [0.2]}",
                   "experiment.params.scaling_seconds=0.25", "experiment.params.resolution_factors=[2.0]",
                   "experiment.params.variants_drones=[rod]", "experiment.params.variants_seconds=0.25",
                   "experiment.params.deviation_seconds=0.25", "experiment.params.mass_scaling=0.02",
                   f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "bench_sim.csv")
    assert list(table["series"]) == ["drone", "drone", "resolution", "scaling"] + ["variant"] * 4
    assert list(table["element"]) == ["linear"] + ["quadratic"] * 7
    # the variants: float32 stays on float64's flight; scaling buys a step for added inertia
    assert metrics["rod_float32_position_deviation_end"] < 1e-5 and metrics["rod_float64_scaled_step_gain"] > 1
    assert 0 < metrics["rod_float64_scaled_added_mass_fraction"] <= 0.02 and metrics["rod_float32_kernel_speedup"] > 0
    assert table["edge_length"].iloc[3] == 0.2 and (tmp_path / "bench_sim.png").exists()
    assert (tmp_path / "variants.png").exists()
    # the rod's default mesh: quadratic elements bend like the converged body, linear ones lock
    assert abs(metrics["rod_quadratic_bend_error"]) < 0.05 and metrics["rod_linear_bend_error"] < -0.2
    assert np.isfinite(table["bend_error"][:4]).all() and (table["blowups"].dropna() == 0).all()
    assert metrics["rod_quadratic_realtime_factor"] > 0
    saved = OmegaConf.load(tmp_path / "config.yaml")
    assert saved.drone.name == "rod" and saved.cache_dir == cache_dir
    (tmp_path / "bench_sim.csv").unlink()
    assert run_experiment(cfg, tmp_path) == json.loads((tmp_path / "metrics.json").read_text())
    assert not (tmp_path / "bench_sim.csv").exists()  # skipped: metrics.json was there

    # the variant rows alone (drones [] = none): no converged references, no accuracy figure
    only = make_cfg("experiment=bench_sim", "drone=rod", "experiment.params.drones=[]",
                    "experiment.params.scaling_drone=null", "experiment.params.resolution_factors=[]",
                    "experiment.params.variants_drones=[rod]", "experiment.params.variants_seconds=0.25",
                    "experiment.params.deviation_seconds=0.25", "experiment.params.mass_scaling=0.02",
                    f"cache_dir={cache_dir}")
    run_experiment(only, tmp_path / "variants")
    assert set(pd.read_csv(tmp_path / "variants" / "bench_sim.csv")["series"]) == {"variant"}
    assert (tmp_path / "variants" / "variants.png").exists() and not (tmp_path / "variants" / "bench_sim.png").exists()


def test_validate_fem_runs_shrunk_and_matches_the_stored_reference(tmp_path, cache_dir):
    """The structured-mesh cases are deterministic: a shrunk run reproduces the committed
    full run's numbers for the cases it shares (results/validate_fem/metrics.json)."""
    cfg = make_cfg("experiment=validate_fem", "experiment.params.layers.linear={2d: [1, 2], 3d: [1]}",
                   "experiment.params.layers.quadratic={2d: [1], 3d: [1]}", "experiment.params.drone_edge_length=null",
                   "experiment.params.drones=[rod]", f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    assert (tmp_path / "cantilever.png").exists() and (tmp_path / "drones.png").exists()
    assert abs(metrics["rod_quadratic_compliance_error"]) < 0.05 and metrics["rod_linear_compliance_error"] < -0.2
    # the second yardstick: locked linear elements ring more than twice as high, quadratic ones
    # within 1% over the first eight free-free modes
    assert abs(metrics["rod_quadratic_freq_error_max"]) < 0.01 and metrics["rod_linear_freq_error"] > 1.0
    reference = json.loads((Path(__file__).resolve().parents[1] / "results" / "validate_fem" / "metrics.json").read_text())
    for key in ("rigid_rise_error", "sag_error_linear_structured_2D_2layers", "freq_error_linear_structured_2D_2layers",
                "sag_error_linear_structured_3D_1layers", "freq_error_linear_structured_3D_1layers",
                "sag_error_quadratic_structured_2D_1layers", "sag_error_quadratic_structured_3D_1layers",
                "freq_error_quadratic_structured_3D_1layers"):
        assert metrics[key] == pytest.approx(reference[key], rel=1e-3, abs=1e-4), key


def test_gallery_runs_shrunk(tmp_path, cache_dir):
    cfg = make_cfg("experiment=gallery", "experiment.params.drones=[rod,bunny]", f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    assert metrics["rod_elements"] > 0 and (tmp_path / "drones.png").exists()


def test_bench_sim_reports_a_blow_up_in_its_table(cache_dir):
    """A timing that blows up (here: any vertex faster than 0.05 m/s counts as a runaway) is
    counted and named in the row, not reset silently."""
    from sdexp.eval.bench_sim import time_drone
    from sdexp.sim.drone import build_drone
    cfg = make_cfg("drone=rod", "sim.max_speed=0.05", f"cache_dir={cache_dir}")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    row = time_drone(drone, cfg.drone, cfg, seconds=0.25, seed=0)
    assert row["blowups"] > 0 and "runaway_speed" in row["blowup_detail"]


@pytest.mark.parametrize("drone", [*DRONES, "tripod"])
def test_a_drone_read_by_name_is_the_drone_hydra_composes(drone):
    """conf.drone (what the fleet and the other multi-drone experiments read) applies a drone
    file's defaults list as Hydra does: the tripod builds on custom.yaml."""
    from sdexp import conf
    assert conf.drone(drone) == make_config(f"drone={drone}").drone


def _running_in_group(pgid: int) -> list[str]:
    """The processes of process group ``pgid`` that run (not zombies: a container's PID 1 may not
    reap the orphans that ended), each as its /proc stat line."""
    running = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:   # ended meanwhile
            continue
        state, _, group = text.rpartition(")")[2].split()[:3]
        if int(group) == pgid and state != "Z":
            running.append(text)
    return running


def test_ctrl_c_ends_a_run_at_once_leaving_no_worker_no_lock_and_a_resumable_folder(tmp_path, cache_dir):
    """Ctrl-C as a terminal sends it (SIGINT to the whole process group) in the data generation of
    a run with two workers and far more data than it will make: the run ends within seconds,
    its workers with it, with one line that says how to resume, its lock released and its config
    kept, and nothing leaked (Python's resource tracker would name leaked semaphores)."""
    import os
    import signal
    import time
    from tests.eval.references import SHRUNK
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "sdexp.cli", "experiment=sota", *SHRUNK, "data.samples=2000000",
                             "data.workers=2", f"cache_dir={cache_dir}", f"hydra.run.dir={out}"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        before = []
        for line in proc.stdout:   # up to the data generation's start, then its workers' start
            before.append(line)
            if "data generation" in line and "started" in line:
                break
        time.sleep(1.0)
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        after, _ = proc.communicate(timeout=30)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, "".join(before) + after
    assert took < 3.0, f"{took:.1f} s"
    assert f"sdexp: interrupted (Ctrl-C): {out} keeps what the run finished, and the same command resumes it" in after
    assert "Traceback" not in after and "leaked" not in after, after
    assert "data generation rod (2 workers): stopped after" in after
    time.sleep(0.5)
    assert _running_in_group(proc.pid) == []   # no worker left

    assert not (out / ".sdexp-run.lock").exists() and (out / "config.yaml").exists()
    assert "interrupted (Ctrl-C)" in (out / "cli.log").read_text()
