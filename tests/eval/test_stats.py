"""sdexp experiment=report: statistics over a sweep's jobs, and a clear error for a folder that
holds none."""
import json
import math
import os
import subprocess
import sys

import pandas as pd
import pytest
import yaml

from sdexp.errors import EXIT_USER_ERROR, UserError
from sdexp.eval import stats


def _job(folder, n, seed, error, survived, experiment="nsweep"):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(yaml.safe_dump({
        "seed": seed, "cache_dir": f"/cache/{seed}", "control": {"n": n, "r": 2.0},
        "experiment": {"name": experiment, "params": {"seconds": 20.0}}}))
    (folder / "metrics.json").write_text(json.dumps({
        "ours_final_error": error, "ours_survived": survived, "ours_failure": "" if survived else "tilt",
        "ours_survival_time": 20.0 if survived else 3.5, "rigid_lqr_final_error": 5.0 + seed}))


@pytest.fixture
def sweep(tmp_path):
    """control.n in {5, 10} x seed in {0, 1, 2}, in Hydra's folder names."""
    root = tmp_path / "multirun"
    errors = {5: [1.0, 2.0, 3.0], 10: [0.5, 0.5, 0.8]}
    for n, values in errors.items():
        for seed, e in enumerate(values):
            _job(root / f"control.n={n},seed={seed}", n, seed, e, survived=not (n == 5 and seed == 2))
    (root / "multirun.yaml").write_text("hydra: {}\n")
    (root / ".submitit" / "123").mkdir(parents=True)   # not a job
    return root


def test_the_t_interval_is_the_textbook_one():
    s = stats.interval([1.0, 2.0, 3.0])
    half = 4.302652729911275 / math.sqrt(3)   # t(0.975, 2) s / sqrt(n), s = 1
    assert s["n"] == 3 and s["mean"] == 2.0 and s["std"] == pytest.approx(1.0)
    assert (s["ci_low"], s["ci_high"]) == pytest.approx((2.0 - half, 2.0 + half))
    wide = stats.interval([1.0, 2.0, 3.0], confidence=0.99)
    assert wide["ci_high"] - wide["ci_low"] > s["ci_high"] - s["ci_low"]
    one = stats.interval([4.0, float("nan"), None])   # non-finite values are not counted
    assert one["n"] == 1 and one["mean"] == 4.0 and math.isnan(one["ci_low"])


def test_jobs_are_grouped_by_their_config_other_than_the_seed(sweep):
    table = stats.aggregate(sweep)
    assert list(dict.fromkeys(table["group"])) == ["n=5", "n=10"]   # numeric order; cache_dir, seed ignored
    row = table[(table["group"] == "n=5") & (table["metric"] == "ours_final_error")].iloc[0]
    assert (row["n"], row["mean"], row["kind"], row["seeds"]) == (3, 2.0, "number", "0 1 2")
    assert row["ci_high"] - row["mean"] == pytest.approx(4.302652729911275 / math.sqrt(3))
    assert "Student t 95%" in row["method"]
    count = table[(table["group"] == "n=5") & (table["metric"] == "ours_survived")].iloc[0]
    assert count["summary"] == "ours survived 2 of 3" and count["true"] == 2 and count["kind"] == "count"
    assert table[(table["group"] == "n=10") & (table["metric"] == "ours_survived")].iloc[0]["summary"] == \
        "ours survived 3 of 3"
    assert "ours_failure" not in set(table["metric"])   # strings are not aggregated
    assert table["n"].max() == 3 and set(table["n"]) == {3}


def test_metric_groups_gather_a_quantity_over_controllers():
    groups = stats.metric_groups(["ours_final_error", "ours_survival_time", "ours_max_tilt_deg",
                                  "rigid_lqr_final_error", "rigid_lqr_survival_time", "rigid_lqr_max_tilt_deg",
                                  "fold_limit_deg"])
    assert groups["final_error"] == [("ours", "ours_final_error"), ("rigid_lqr", "rigid_lqr_final_error")]
    assert groups["max_tilt_deg"] == [("ours", "ours_max_tilt_deg"), ("rigid_lqr", "rigid_lqr_max_tilt_deg")]
    assert groups["fold_limit_deg"] == [("", "fold_limit_deg")]


@pytest.mark.parametrize("make", ["missing", "file", "empty", "no_metrics"])
def test_a_folder_without_jobs_is_a_user_error_naming_it(tmp_path, make):
    path = tmp_path / "sweep"
    if make == "file":
        path.write_text("")
    elif make == "empty":
        path.mkdir()
    elif make == "no_metrics":
        (path / "seed=0").mkdir(parents=True)
        (path / "seed=0" / "config.yaml").write_text("seed: 0\n")
    with pytest.raises(UserError, match=str(path.resolve())):
        stats.find_jobs(path)


def sdexp(*args, cwd):
    return subprocess.run([sys.executable, "-m", "sdexp.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "HYDRA_FULL_ERROR": ""})


def test_the_report_command_writes_the_table_and_the_plot(sweep, tmp_path):
    res = sdexp("experiment=report", f"sweep_dir={sweep}", f"hydra.run.dir={tmp_path / 'report'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    table = pd.read_csv(tmp_path / "report" / "stats.csv")
    assert set(table["group"]) == {"n=5", "n=10"} and "ours survived 2 of 3" in set(table["summary"])
    assert (tmp_path / "report" / "stats.png").stat().st_size > 0
    metrics = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert metrics["jobs"] == 6 and metrics["groups"] == 2
    assert "ours survived 2 of 3" in (tmp_path / "report" / "cli.log").read_text()
    # a report run inside the sweep folder is not one of its jobs
    res = sdexp("experiment=report", f"experiment.params.sweep_dir={sweep}",
                f"hydra.run.dir={sweep / 'report'}", cwd=tmp_path)
    assert res.returncode == 0 and json.loads((sweep / "report" / "metrics.json").read_text())["jobs"] == 6


@pytest.mark.parametrize("args", [["sweep_dir={empty}"], ["experiment.params.sweep_dir={empty}"], []])
def test_the_report_command_on_a_wrong_folder_is_one_line_exit_2(tmp_path, args):
    (tmp_path / "empty").mkdir()
    res = sdexp("experiment=report", *[a.format(empty=tmp_path / "empty") for a in args], cwd=tmp_path)
    err = res.stderr.strip()
    assert res.returncode == EXIT_USER_ERROR and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert (str(tmp_path / "empty") if args else "sweep_dir") in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]   # no run folder left behind


def test_a_scatter_draws_one_point_per_job_and_names_a_metric_no_job_has(sweep, tmp_path):
    path = tmp_path / "scatter.png"
    assert stats.scatter(sweep, ["ours_survival_time", "ours_final_error", "ours_survived"], path, [10.0, 1.0]) == 6
    assert path.stat().st_size > 0
    with pytest.raises(UserError) as err:
        stats.scatter(sweep, ["ours_final_error", "ours_fold"], tmp_path / "no.png")
    assert "'ours_fold'" in str(err.value) and "ours_final_error" in str(err.value)
    assert not (tmp_path / "no.png").exists()


def test_the_report_command_checks_its_scatter_before_writing(sweep, tmp_path):
    res = sdexp("experiment=report", f"sweep_dir={sweep}", "experiment.params.scatter=[ours_final_error,fold]",
                f"hydra.run.dir={tmp_path / 'report'}", cwd=tmp_path)
    err = res.stderr.strip()
    assert res.returncode == EXIT_USER_ERROR and "'fold'" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "report").exists()
    res = sdexp("experiment=report", f"sweep_dir={sweep}", "experiment.params.scatter=[ours_survival_time,ours_final_error]",
                "experiment.params.scatter_lines=[null,1.0]", f"hydra.run.dir={tmp_path / 'report'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "report" / "scatter.png").stat().st_size > 0


@pytest.mark.parametrize("override, words", [("experiment.params.scatter=[ours_final_error]", "[x, y]"),
                                             ("experiment.params.scatter_lines=[1,2,3]", "scatter_lines")])
def test_a_scatter_of_the_wrong_size_is_named(sweep, tmp_path, override, words):
    res = sdexp("experiment=report", f"sweep_dir={sweep}", override, f"hydra.run.dir={tmp_path / 'report'}", cwd=tmp_path)
    err = res.stderr.strip()
    assert res.returncode == EXIT_USER_ERROR and words in err and len(err.splitlines()) == 1, err
