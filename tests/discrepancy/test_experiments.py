"""The record and discrepancy experiments through the experiment runner, shrunk."""
import json

import pytest

from sdexp.errors import UserError
from sdexp.eval.run import run_experiment
from tests.discrepancy.conftest import SMALL
from tests.conftest import make_cfg


def test_record_then_discrepancy(tmp_path, cache_dir):
    rec = make_cfg(*SMALL, "experiment=record", "sim.effects=[{name: thrust_loss, rotor: 1, fraction: 0.35}]",
                   f"cache_dir={cache_dir}", "seed=5")
    m = run_experiment(rec, tmp_path / "rec")
    logs = tmp_path / "rec" / "logs"
    assert m["flights"] == 4 and len(list(logs.glob("*.csv"))) == 4
    meta = json.loads((logs / "meta.json").read_text())
    assert meta["drone"] == "leaf" and meta["sample_rate"] == 100.0 and "thrust_loss" not in json.dumps(meta)
    dis = make_cfg(*SMALL, "experiment=discrepancy", f"discrepancy.measured={logs}", f"cache_dir={cache_dir}")
    m = run_experiment(dis, tmp_path / "dis")
    assert m["effects"][:1] == ["thrust_loss"]
    report = json.loads((tmp_path / "dis" / "report.json").read_text())
    assert report["effects"][0]["params"]["rotor"] == 1


def test_discrepancy_needs_measured_logs(tmp_path, cache_dir):
    with pytest.raises(UserError, match="discrepancy.measured"):
        run_experiment(make_cfg(*SMALL, "experiment=discrepancy", f"cache_dir={cache_dir}"), tmp_path)
    with pytest.raises(UserError, match="not a folder"):
        run_experiment(make_cfg(*SMALL, "experiment=discrepancy", f"discrepancy.measured={tmp_path}/nope",
                                f"cache_dir={cache_dir}"), tmp_path / "o")
