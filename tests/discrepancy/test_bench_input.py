"""The discrepancy bench's bad input (issue 54): its parameters that the folders and the drone must
allow are refused in one line naming the key, the value and what is allowed, before the run folder
is made; a scenario that raises is a row that says why, and the others are scored without it.
No bench runs here."""
import errno
import json

import numpy as np
import pandas as pd
import pytest

from sdexp.discrepancy import bench
from sdexp.errors import UserError
from sdexp.eval.run import run_experiment
from tests.conftest import make_cfg


def refused(tmp_path, cache_dir, *overrides) -> str:
    out = tmp_path / "run"
    before = sorted(out.rglob("*")) if out.exists() else None
    with pytest.raises(UserError) as info:
        run_experiment(make_cfg("experiment=discrepancy_bench", f"cache_dir={cache_dir}", *overrides), out)
    assert (sorted(out.rglob("*")) if out.exists() else None) == before   # refused before anything is written
    return str(info.value)


def _earlier_run(folder, scen_dir=None, columns=("id", "verdict", "true_effects")):
    """An earlier bench's scenarios.csv (one row that ran, one that failed) and, with ``scen_dir``,
    the scenario folder of the one that ran."""
    folder.mkdir(parents=True)
    rows = [{"id": "wind-b0", "verdict": "effect", "true_effects": "[]"},
            {"id": "null-0", "verdict": bench.FAILED, "true_effects": "[]"}]
    pd.DataFrame(rows)[list(columns)].to_csv(folder / "scenarios.csv", index=False)
    if scen_dir is not None:
        (scen_dir / "wind-b0" / "logs").mkdir(parents=True)
        (scen_dir / "wind-b0" / "workflow").mkdir()
        (scen_dir / "wind-b0" / "workflow" / "sim_fitted.yaml").write_text("effects: []\n")


def test_rescore_needs_an_earlier_runs_table_and_its_scenario_folders(tmp_path, cache_dir):
    message = refused(tmp_path, cache_dir, "experiment.params.rescore=true")
    assert "experiment.params.rescore = true" in message and "scenarios.csv does not exist" in message
    assert "allowed only in the folder of an earlier bench run" in message
    _earlier_run(tmp_path / "run")
    message = refused(tmp_path, cache_dir, "experiment.params.rescore=true")
    assert "scenario wind-b0's" in message and "logs does not exist" in message   # the failed row needs none
    (tmp_path / "run" / "scenarios.csv").write_text("id,verdict\nwind-b0,effect\n")
    assert "has no column 'true_effects'" in refused(tmp_path, cache_dir, "experiment.params.rescore=true")


def test_rescore_passes_its_check_where_the_earlier_run_is(tmp_path, cache_dir):
    from sdexp.eval.run import Run, typed
    _earlier_run(tmp_path / "run", tmp_path / "scen")
    cfg = typed(make_cfg("experiment=discrepancy_bench", "experiment.params.rescore=true",
                         f"experiment.params.scenario_dir={tmp_path / 'scen'}", f"cache_dir={cache_dir}"))
    bench.check(cfg.experiment.params, tmp_path / "run", cfg.drone, cfg.sim, cache_dir, 0)


@pytest.mark.parametrize("where", ["afile", "afile/sub"])
def test_a_scenario_dir_that_is_or_lies_in_a_file_is_refused(tmp_path, cache_dir, where):
    (tmp_path / "afile").write_text("not a folder")
    message = refused(tmp_path, cache_dir, f"experiment.params.scenario_dir={tmp_path / where}")
    assert f"experiment.params.scenario_dir = '{tmp_path / where}'" in message
    assert "is a file: allowed a folder" in message


def test_a_reaction_torque_on_a_2d_drone_is_refused_not_dropped(tmp_path, cache_dir):
    message = refused(tmp_path, cache_dir, "drone=rod", "experiment.params.effects=[wind,rotor_reaction_torque]")
    assert "experiment.params.effects = ['wind', 'rotor_reaction_torque']" in message
    assert "needs a 3D drone" in message and "allowed on this 2D drone rotor_drag" in message
    assert "rotor_reaction_torque" not in bench.effect_names(type("P", (), {"effects": None}), 2)   # the library's: left out


def test_only_names_scenarios_of_this_bench_before_anything_is_written(tmp_path, cache_dir):
    message = refused(tmp_path, cache_dir, "experiment.params.only=[payload-c0]", "experiment.params.effects=[payload]")
    assert "experiment.params.only: unknown scenario(s) ['payload-c0']" in message and "'payload-b0'" in message


def _scenario():
    return {"id": "wind-b0", "kind": "single", "truth": ["wind"], "effects": [{"name": "wind", "velocity": [1.0, 0, 0]}],
            "seed": 1}


def test_a_scenario_that_raises_is_a_row_with_its_reason(monkeypatch):
    def boom(*args):
        raise np.linalg.LinAlgError("Singular matrix")
    monkeypatch.setattr(bench, "_scenario_row", boom)
    reported = []
    row = bench.run_scenario(_scenario(), None, None, None, None, "unused", "unused", report=reported.append)
    assert row["verdict"] == bench.FAILED and row["error"] == "LinAlgError: Singular matrix"
    assert row["truth"] == "wind" and json.loads(row["true_effects"]) == _scenario()["effects"]
    assert reported == [1]   # counted as done: the bench goes on
    # nothing to rescore in it
    assert bench.rescore_row(row, None, None, None, None, "unused", "unused") is row

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(bench, "_scenario_row", full)
    with pytest.raises(OSError):   # a full disk ends the bench: every scenario after would fail too
        bench.run_scenario(_scenario(), None, None, None, None, "unused", "unused")


def test_failed_scenarios_are_listed_with_why_and_not_scored():
    ran = {"ties": "", "gap_reduction": 0.9, "oracle_gap_reduction": 0.9, "param_error": 0.1, "param_covered": True}
    t = pd.DataFrame([
        {**ran, "id": "wind-b0", "kind": "single", "truth": "wind", "top1": "wind", "verdict": "effect", "named": "wind"},
        {**ran, "id": "null-0", "kind": "null", "truth": "none", "top1": "none", "verdict": "none", "named": ""},
        {"id": "null-1", "kind": "null", "truth": "none", "top1": bench.FAILED, "verdict": bench.FAILED, "named": "",
         "ties": "", "error": "LinAlgError: Singular matrix"},
    ])
    m = bench.summarize(t)
    assert m["scenarios"] == 3 and m["scenarios_failed"] == 1
    assert m["failed_scenarios"] == {"null-1": "LinAlgError: Singular matrix"}
    assert m["null_false_positive_rate"] == 0.0 and m["top1_accuracy"] == 1.0   # the failure is no answer
    nothing = bench.summarize(t[t.verdict == bench.FAILED])
    assert nothing["scenarios_failed"] == 1 and nothing["targets_met"] == {}
