"""experiment=rl_baseline: a Stable-Baselines3 agent scored beside ours on the same seeded episodes,
at every budget of one training run; resumed from its jobs; bad params refused by name."""
import json
import sys

import pandas as pd
import pytest

from sdexp.errors import UserError
from sdexp.eval.run import run_experiment, typed
from tests.conftest import make_cfg
from tests.eval.references import SHRUNK

pytest.importorskip("stable_baselines3", reason="the rl extra: pip install -e '.[rl]'")

# learning on the full rod (the reduced model's build is tested where it is made), two budgets of
# one SAC run past its 100 random warm-up transitions, one scored hover episode each
TINY = [*SHRUNK, "experiment=rl_baseline", "data.sim_model=null", "experiment.params.tasks=[hover]",
        "experiment.params.budgets=[150,300]", "experiment.params.episodes=1", "experiment.params.seeds=[0]",
        "experiment.params.workers=1"]


def test_the_agent_and_ours_are_scored_on_the_same_episodes_and_a_rerun_resumes(tmp_path, cache_dir, caplog):
    cfg = make_cfg(*TINY, f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "rl_baseline.csv")
    assert sorted(map(tuple, table[["controller", "transitions"]].values.tolist())) == \
        [("ours", 800), ("sac", 150), ("sac", 300)]
    assert (table["tolerance"] == 0.1).all() and (table["within"] == (table["survived"] & (table["final_error"] <= 0.1))).all()
    # every scored episode runs the hover's 10 s unless it ends early, and says why
    ended = table[~table["survived"]]
    assert (ended["failure"].str.len() > 0).all() and (table[table["survived"]]["survival_time"] >= 9.99).all()
    assert (tmp_path / "jobs" / "hover_seed0_sac" / "150.zip").exists() and (tmp_path / "jobs" / "hover_seed0_sac" / "300.zip").exists()
    assert metrics["hover_sac_300_episodes"] == 1 and metrics["hover_ours_transitions"] == 800
    assert metrics["hover_sac_150_train_seconds_median"] < metrics["hover_sac_300_train_seconds_median"]
    assert (tmp_path / "rl_baseline.png").exists()

    # resumed (metrics.json gone, the jobs kept): nothing trains or flies again
    jobs = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "jobs").glob("*.json")}
    (tmp_path / "metrics.json").unlink()
    with caplog.at_level("INFO"):
        run_experiment(cfg, tmp_path)
    assert "2 of 2 jobs done before" in caplog.text
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "jobs").glob("*.json")} == jobs
    assert pd.read_csv(tmp_path / "rl_baseline.csv").equals(table)


def test_the_agent_learns_where_the_data_are_made_and_is_scored_on_the_simulator():
    from sdexp.envs.rl_baseline import _configs
    cfg = typed(make_cfg("experiment=rl_baseline"))
    learn, scored = _configs(cfg, 3)
    assert (learn.sim.model, scored.sim.model) == ("reduced", "full") and learn.seed == scored.seed == 3
    assert learn.data.workers == learn.model.threads == learn.sim.threads == 1
    cfg = typed(make_cfg("experiment=rl_baseline", "data.sim_model=null"))
    assert _configs(cfg, 0)[0].sim.model == "full"


@pytest.mark.parametrize("override, words", [
    ("experiment.params.budgets=[0]", ["experiment.params.budgets", "> 0"]),
    ("experiment.params.budgets=[100,100]", ["experiment.params.budgets", "distinct"]),
    ("experiment.params.tasks=[velocity]", ["experiment.params.tasks", "hover or reach"]),
    ("experiment.params.algorithm=dqn", ["experiment.params.algorithm", "sac or ppo"]),
    ("experiment.params.episodes=0", ["experiment.params.episodes", "> 0"]),
])
def test_bad_params_are_refused_by_name_before_anything_is_written(tmp_path, override, words):
    with pytest.raises(UserError) as err:
        run_experiment(make_cfg("experiment=rl_baseline", override), tmp_path)
    for w in words:
        assert w in str(err.value), str(err.value)
    assert not (tmp_path / "rl_baseline.csv").exists() and not (tmp_path / "jobs").exists()


def test_without_stable_baselines3_the_run_says_which_extra_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)   # import fails
    with pytest.raises(UserError, match=r'pip install -e "\.\[rl\]"'):
        run_experiment(make_cfg("experiment=rl_baseline"), tmp_path)
    assert not (tmp_path / "jobs").exists()
