"""A drone of one's own flies: the shipped example (drone=tripod, an STL made by
examples/make_tripod.py) identified from tiny data and hovered by ours for a second, reduced as
the other control experiments are (tests/eval/references.py's SHRUNK)."""
import numpy as np

from sdexp.eval.experiments import run_experiment
from tests.eval.references import SHRUNK
from tests.test_cli import make_cfg

SECONDS = 1.0


def test_ours_hovers_the_tripod_from_its_stl(tmp_path, cache_dir):
    cfg = make_cfg(*SHRUNK[1:], "drone=tripod", f"cache_dir={cache_dir}", "experiment=sota",
                   f"experiment.params.seconds={SECONDS}", "experiment.params.start=[0,0,0]",
                   "experiment.params.target=[0,0,0]", "experiment.params.controllers=[ours]",
                   "experiment.params.animate=[]")
    m = run_experiment(cfg, tmp_path)
    # it stays up: with its rotors off it would fall g t^2 / 2 = 4.9 m in this second
    assert m["ours_survival_time"] >= SECONDS - 1e-9
    assert np.isfinite(m["ours_final_error"]) and m["ours_final_error"] < 0.5
