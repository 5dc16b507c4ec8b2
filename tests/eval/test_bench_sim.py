"""experiment=bench_sim: the models parameter (the reduced model's rows beside the full one's) and
a diverged run's rows. Shrunk: the rod (96 quadratic triangles), no refinement series."""
import json
import math

import pandas as pd
import pytest

from sdexp.errors import UserError
from sdexp.eval.run import run_experiment
from tests.conftest import make_cfg, make_config

# the rod alone: no resolution or refinement series, no variants unless asked
SHRUNK = ("experiment=bench_sim", "drone=rod", "experiment.params.drones=[rod]", "experiment.params.elements=[quadratic]",
          "experiment.params.scaling_drone=null", "experiment.params.resolution_factors=[]",
          "experiment.params.variants_drones=[]", "experiment.params.seconds=0.5")
# a small reduced model of the rod (reduced_gates' shrunk test builds the same in seconds)
SMALL_REDUCED = ("sim.reduced.snapshot_seconds=3", "sim.reduced.basis=20", "sim.reduced.modal_derivatives=2",
                 "sim.reduced.cubature=40")


@pytest.mark.parametrize("models, words", [
    ("[full,nope]", ["experiment.params.models = ['full', 'nope'] is out of range", "allowed full or reduced each"]),
    ("[]", ["experiment.params.models = []", "allowed a non-empty list of distinct models, each full or reduced"]),
    ("[full,full]", ["experiment.params.models = ['full', 'full']", "distinct"]),
])
def test_the_models_parameter_names_its_choices(models, words):
    with pytest.raises(UserError) as info:
        make_config("experiment=bench_sim", f"experiment.params.models={models}")
    assert all(w in str(info.value) for w in words), str(info.value)


def test_bench_sim_refuses_sim_model_reduced_before_writing(tmp_path):
    with pytest.raises(UserError, match=r"sim.model = reduced: bench_sim times the models experiment.params.models"):
        run_experiment(make_cfg(*SHRUNK, "sim.model=reduced"), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_the_reduced_model_is_timed_beside_the_full_one(tmp_path, cache_dir):
    cfg = make_cfg(*SHRUNK, "experiment.params.models=[full,reduced]", *SMALL_REDUCED, f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "bench_sim.csv")
    assert list(table["model"]) == ["full", "reduced"] and set(table["series"]) == {"drone"}
    full, red = table.iloc[0], table.iloc[1]
    for row in (full, red):
        assert row["blowups"] == 0 and row["realtime_factor"] > 0 and row["us_per_substep"] > 0
    assert red["elements"] <= 40 and red["basis"] == 20 and red["substeps_per_step"] < full["substeps_per_step"]
    # the bench's +-Tmax holds take this small model out of its fitted range: restarted and counted, not a blow-up
    assert red["left_range"] == red["blowup_detail"].count("left_reduced_range at")
    assert red["speedup_vs_full"] > 0 and pd.isna(full["speedup_vs_full"])   # the ratio on the reduced row only
    # the accuracy against the converged body on the full row; the reduced row's statics against the full model's
    assert math.isfinite(full["bend_error"]) and pd.isna(red["bend_error"]) and abs(red["compliance_error_vs_full"]) < 0.5
    assert metrics["rod_quadratic_reduced_speedup_vs_full"] == pytest.approx(red["speedup_vs_full"])
    assert metrics["rod_quadratic_realtime_factor"] > 0   # the full model's keys as before


def test_a_reduced_model_that_refuses_the_config_is_a_row_with_its_reason(tmp_path, cache_dir):
    cfg = make_cfg(*SHRUNK, "experiment.params.models=[full,reduced]", "sim.ground=-5", f"cache_dir={cache_dir}")
    run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "bench_sim.csv")
    full, red = table.iloc[0], table.iloc[1]
    assert full["realtime_factor"] > 0 and pd.isna(red["realtime_factor"]) and pd.isna(red["speedup_vs_full"])
    assert red["reason"].startswith("refused: sim.model = reduced cannot carry a ground plane") and "sim.ground" in red["reason"]


def test_a_substep_past_the_stable_one_is_a_diverged_row_not_a_traceback(tmp_path, cache_dir):
    """sdexp experiment=bench_sim drone=rod experiment.params.drones=[rod] sim.substep=0.01 (10x the
    rod's stable step): every timing blows up; the rows count it, with no speed and no energy drift,
    and metrics.json stays JSON (null, not Infinity)."""
    cfg = make_cfg(*SHRUNK, "sim.substep=0.01", "experiment.params.variants_drones=[rod]",
                   "experiment.params.variants_seconds=0.25", "experiment.params.deviation_seconds=0.25",
                   "experiment.params.mass_scaling=0.02", f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "bench_sim.csv")
    drone = table[table["series"] == "drone"].iloc[0]
    assert drone["blowups"] >= 1 and pd.isna(drone["realtime_factor"]) and "at 0." in drone["blowup_detail"]
    assert metrics["rod_quadratic_realtime_factor"] is None and metrics["rod_quadratic_blowups"] >= 1
    variants = table[table["series"] == "variant"]
    assert len(variants) == 4 and (variants["blowups"] >= 1).all()
    assert variants["realtime_factor"].isna().all() and variants["energy_drift"].isna().all()
    assert variants["blowup_detail"].str.contains("energy check: the excitation diverged").all()
    assert metrics["rod_float64_realtime_factor"] is None and metrics["rod_float64_energy_drift"] is None
    json.loads((tmp_path / "metrics.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in metrics.json"))
