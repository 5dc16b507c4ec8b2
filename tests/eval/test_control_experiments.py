"""Every control experiment composes and runs shrunk (a tiny rod or star model, fractions of a
second of flight), writing its tables and plots; the regression against stored reference
metrics is in test_control_regression.py."""
import json

import numpy as np
import pandas as pd
import pytest

from sdexp.eval.experiments import run_experiment
from tests.model.test_dynamics import SHRUNK
from tests.test_cli import make_cfg

NEURAL = ["control.neural.iterations=2", "control.neural.horizon=3", "control.neural.batch=4"]


def run(tmp_path, cache_dir, *overrides):
    cfg = make_cfg(*SHRUNK, f"cache_dir={cache_dir}", "sim.threads=1", *overrides)
    return run_experiment(cfg, tmp_path)


def test_sota_runs_shrunk_with_every_controller(tmp_path, cache_dir):
    m = run(tmp_path, cache_dir, "experiment=sota", "experiment.params.seconds=0.3",
            "experiment.params.start=[0,0]", "experiment.params.target=[1,1]", *NEURAL)
    table = pd.read_csv(tmp_path / "sota.csv")
    assert list(table["controller"]) == ["ours", "rigid_lqr", "geometry_lqr", "neural"]
    assert {"paper_survival_time", "paper_final_error", "paper_thrust_usage"} <= set(table.columns)
    for name in table["controller"]:
        assert (tmp_path / f"trajectory_{name}.csv").exists()
        assert 0 < m[f"{name}_survival_time"] <= 0.3 + 1e-9
        assert m[f"{name}_thrust_usage"] <= 30 * 5 * 10.0 + 1e-6   # steps x rotors x Tmax
    assert (tmp_path / "sota.png").exists() and (tmp_path / "config.yaml").exists()
    assert m["ours_ms_per_relinearization"] > 0


def test_nsweep_runs_shrunk(tmp_path, cache_dir):
    m = run(tmp_path, cache_dir, "experiment=nsweep", "experiment.params.seconds=0.2",
            "experiment.params.start=[0,0]", "experiment.params.target=[1,0]", "experiment.params.n_values=[1,5]")
    table = pd.read_csv(tmp_path / "nsweep.csv")
    assert list(table["n"]) == [1, 5] and np.allclose(table["relinearization_hz"], [100, 20])
    assert (tmp_path / "nsweep.png").exists() and "n5_final_error" in m


def test_ablation_fixed_point_runs_shrunk(tmp_path, cache_dir):
    m = run(tmp_path, cache_dir, "experiment=ablation_fixed_point", "experiment.params.seconds=0.2",
            "experiment.params.trials=64", "experiment.params.descent_steps=20", "experiment.params.noise_levels=[0,0.8]")
    table = pd.read_csv(tmp_path / "ablation_fixed_point.csv")
    assert len(table) == 4 and set(table["mode"]) == {"fixed", "relinearized"}
    assert np.isfinite(m["fixed_point_residual"]) and (tmp_path / "ablation_fixed_point.png").exists()


def test_hover_deform_runs_shrunk(tmp_path, cache_dir):
    m = run(tmp_path, cache_dir, "experiment=hover_deform", "experiment.params.settle_seconds=0.05",
            "experiment.params.ramp_seconds=0.05", "experiment.params.hold_seconds=0.02")
    assert (tmp_path / "hover_deform.csv").exists() and (tmp_path / "hover_deform.png").exists()
    assert m["max_attitude_deviation_deg"] >= 0 and isinstance(m["paper_band_held"], bool)


def test_bench_control_runs_shrunk(tmp_path, cache_dir):
    m = run(tmp_path, cache_dir, "experiment=bench_control", "experiment.params.samples=10")
    assert m["relinearization_ms"] >= m["jacobians_ms"] > 0 and m["control_step_ms"] > 0
    assert len(pd.read_csv(tmp_path / "bench_control.csv")) == 5


def test_obstacle_runs_shrunk_on_the_star(tmp_path, cache_dir):
    m = run(tmp_path, cache_dir, "experiment=obstacle", "drone=star", "experiment.params.seconds=0.1",
            "experiment.params.fold_start=0.0", "experiment.params.fold_seconds=0.05")
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["hit_obstacle"] is False and saved["passed"] is False   # 0.1 s: nowhere near the gap
    assert 0 <= m["width_reduction_percent"] < 100 and (tmp_path / "obstacle.png").exists()
