"""experiment=reduced_gates, shrunk: every gate is measured and judged on the rod."""
import pandas as pd

from sdexp.eval.reduced_gates import verdict
from sdexp.eval.run import run_experiment
from tests.conftest import make_cfg


def test_reduced_gates_run_shrunk_on_the_rod(tmp_path, cache_dir):
    cfg = make_cfg("experiment=reduced_gates", "drone=rod", "experiment.params.drones=[rod]",
                   "experiment.params.frontier_drone=rod", "experiment.params.frontier=[[12,0,30]]",
                   "experiment.params.recipes=[near_hover]", "experiment.params.flight_seconds=0.3",
                   "experiment.params.energy_seconds=0.1", "experiment.params.workers=1",
                   "sim.reduced.snapshot_seconds=3", "sim.reduced.basis=20", "sim.reduced.modal_derivatives=2",
                   "sim.reduced.cubature=40", f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    gates = pd.read_csv(tmp_path / "gates.csv")
    row = gates.iloc[0]
    # the cubature's rest stiffness fitted on small motions along every basis vector
    assert row["freq_error"] < 0.1 and abs(row["compliance_error"]) < 0.2   # 40 of the 96 elements
    assert 0 <= row["deformation_error"] < 1 and row["realtime_reduced"] > 0 and row["substeps_reduced"] < row["substeps_full"]
    assert row["passes"] == pd.isna(row["why"])   # a reason exactly when it fails (an empty one reads as NaN)
    assert metrics["rod_passes"] == bool(row["passes"])
    assert len(pd.read_csv(tmp_path / "frontier.csv")) == 1
    assert (tmp_path / "gates.png").exists() and (tmp_path / "frontier.png").exists()


def test_a_gate_that_fails_says_why_with_its_numbers():
    row = {"freq_error": 0.004, "bend_error": 0.03, "compliance_error": 0.0, "deformation_error": 0.08,
           "imu_deformation_error": 0.02, "left_range": 1, "energy_drift_full": 0.01, "energy_drift_reduced": 0.005}
    v = verdict(row)
    assert not v["passes"]
    assert "bend +3.0% > 2%" in v["why"] and "deformation error 8.0% > 5%" in v["why"] and "1 flights left" in v["why"]
    assert "frequencies" not in v["why"] and "energy" not in v["why"]
    row.update(bend_error=0.0, deformation_error=0.01, left_range=0)
    assert verdict(row) == {"passes": True, "why": ""}



def test_a_recipe_is_judged_on_its_own_flights():
    row = {"freq_error": 0.0, "bend_error": 0.0, "compliance_error": 0.0, "deformation_error": 0.5,
           "imu_deformation_error": 0.5, "left_range": 1, "energy_drift_full": 0.0, "energy_drift_reduced": 0.0,
           "near_hover_deformation_error": 0.03, "near_hover_imu_deformation_error": 0.04, "near_hover_left_range": 0}
    assert not verdict(row)["passes"] and verdict(row, "near_hover")["passes"]
