"""A drone of one's own flies: the shipped example (drone=tripod, an STL made by
examples/make_tripod.py) identified from tiny data and held up by ours, reduced as the other
control experiments are (tests/eval/references.py's SHRUNK: 800 samples, 2 epochs).

Open (issue 27): with that model ours does not hold the tripod up. Measured here: a 1 s hover
was lost at 0.44 s, and after 0.3 s it was 0.42 m off, about the 0.44 m of a free fall. So the
test is a strict xfail, recording that; the next step is the smallest data and training that
hold it up (more samples, data.around_hover), then drop the mark. With the fleet's recipe and nets in
the heading frame, 13,500 samples hold every seed up for 10 s (results/fleet_tripod/); 2,000 samples
and 10 epochs lose seed 0 at 0.52 s, 4,000 in the heading frame at 0.76 s (scratch, 2026-11-27)."""
import numpy as np
import pytest

from sdexp.eval.run import run_experiment
from tests.eval.references import SHRUNK
from tests.conftest import make_cfg

SECONDS = 0.3


@pytest.mark.xfail(strict=True, reason="SHRUNK's 800-sample model does not hold the tripod up yet (issue 27)")
def test_ours_holds_the_tripod_up_from_its_stl(tmp_path, cache_dir):
    cfg = make_cfg(*SHRUNK[1:], "drone=tripod", f"cache_dir={cache_dir}", "experiment=sota",
                   f"experiment.params.seconds={SECONDS}", "experiment.params.start=[0,0,0]",
                   "experiment.params.target=[0,0,0]", "experiment.params.controllers=[ours]",
                   "experiment.params.animate=[]")
    m = run_experiment(cfg, tmp_path)
    # it stays up: with its rotors off it would fall g t^2 / 2 = 0.44 m in this time
    assert m["ours_survival_time"] >= SECONDS - 1e-9
    assert np.isfinite(m["ours_final_error"]) and m["ours_final_error"] < 0.5 * 9.81 * SECONDS ** 2 / 2


def test_the_fleet_flies_a_drone_of_ones_own_through_its_tasks(tmp_path, cache_dir):
    """`sdexp experiment=fleet experiment.params.drones=[tripod]` (results/fleet_tripod/): a
    drone from a mesh file has no drone.size, so its reach trip comes from its rest shape, and
    its config's defaults list (custom.yaml) is applied when the fleet reads it by name. Reduced:
    the tiny model, 0.3 s flights; every task is a flown row, no job failed."""
    import pandas as pd
    from tests.eval.references import reduced_overrides
    overrides = [o for o in reduced_overrides("fleet", cache_dir) if not o.startswith("experiment.params.drones")]
    m = run_experiment(make_cfg(*overrides, "experiment.params.drones=[tripod]"), tmp_path)
    table = pd.read_csv(tmp_path / "fleet.csv")
    assert m["jobs_failed"] == 0 and set(table["task"]) == {"hover", "reach", "velocity", "deform"}
    reach = table[table["task"] == "reach"]["tolerance"].iloc[0]
    assert reach == pytest.approx(0.1 * 2.49, rel=0.02)   # a tenth of its 2.49 m body
