"""experiment=design_rule: the elephant's rotors, as first drawn on its back, and where the rule
puts them (shrunk: two candidates, short holds)."""
import pandas as pd
import pytest

from sdexp.errors import UserError
from sdexp.eval.design_rule import candidates, distance, with_values
from sdexp.eval.run import run_experiment
from sdexp import conf
from tests.conftest import make_cfg


def test_the_rule_keeps_the_passing_design_nearest_the_drawing(tmp_path, cache_dir):
    cfg = make_cfg("experiment=design_rule", "experiment.params.seconds=2", "experiment.params.workers=1",
                   "experiment.params.drones=[elephant]", "experiment.params.designs.elephant.grid.back_start=[0.25]",
                   "experiment.params.designs.elephant.grid.back_end=[0.5,0.75,0.8]", f"cache_dir={cache_dir}")
    metrics = run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "design_rule.csv").set_index("back_end")
    # as drawn both rotors sit behind the centre of mass: lift and torque need more than Tmax
    assert not table.loc[0.5, "passes"] and table.loc[0.5, "design_rule"].startswith("largest rotor thrust")
    assert table.loc[0.75, "passes"] and table.loc[0.75, "chosen"] and not table.loc[0.8, "chosen"]
    assert table.loc[0.75, "static_hover_share"] <= 0.6 and table.loc[0.75, "distance"] == pytest.approx(0.5)
    assert metrics["elephant_back_end"] == 0.75 and metrics["elephant_committed_is_chosen"]
    assert (tmp_path / "design_rule.png").exists()


def test_candidates_distance_and_values():
    grid = {"back_start": [0.2, 0.25], "back_end": [0.5, 0.75]}
    assert len(candidates(grid)) == 4
    assert distance({"back_start": 0.25, "back_end": 0.75}, {"back_start": 0.25, "back_end": 0.5}) == pytest.approx(0.5)
    peel = with_values(conf.drone("orange_peel"), {"rotor_inset": 0.9, "thickness": 0.12})
    assert peel.params["rotor_inset"] == 0.9 and peel.thickness == 0.12 and peel.params["petal_width"] == 0.9


@pytest.mark.parametrize("args, words", [
    (["+experiment.params.designs.nosuch={grid: {thickness: [0.1]}}"], ["nosuch", "flower"]),
    (["+experiment.params.designs.elephant.grid.nosuch=[0.1]"], ["nosuch", "back_end"]),
    (["+experiment.params.designs.elephant.grid.youngs_modulus=[1e4]"], ["youngs_modulus", "thickness"]),
    (["experiment.params.designs.elephant.grid.back_end=[]"], ["non-empty list"]),
    (["experiment.params.drones=[flower]"], ["flower", "orange_peel, elephant"]),
])
def test_bad_designs_are_refused_by_name(tmp_path, cache_dir, args, words):
    with pytest.raises(UserError) as err:
        run_experiment(make_cfg("experiment=design_rule", *args, f"cache_dir={cache_dir}"), tmp_path)
    for w in words:
        assert w in str(err.value), str(err.value)
    assert not (tmp_path / "design_rule.csv").exists()
