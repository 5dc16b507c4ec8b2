"""The log format: a round trip, and bad input named by file and column with nothing overwritten."""
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from sdexp.discrepancy.logs import channel_names, meta_for, read_logs, write_flight, write_meta
from sdexp.discrepancy.workflow import run_workflow
from sdexp.errors import UserError


def fake_logs(folder, drone, flights=2, rows=60):
    rng = np.random.default_rng(0)
    C = len(channel_names(drone.dim, drone.layout.n_s))
    for i in range(flights):
        t = 0.01 * np.arange(rows)
        write_flight(folder, f"flight_{i:03d}", t, rng.uniform(0, 3, (rows, drone.num_rotors)),
                     rng.normal(size=(rows, C)), drone.dim, drone.layout.n_s)
    write_meta(folder, meta_for(drone, 100.0))


def read(folder, drone):
    return read_logs(folder, drone.name, drone.num_rotors, drone.layout.n_s, drone.dim)


def test_round_trip_and_columns(tmp_path, leaf):
    fake_logs(tmp_path, leaf)
    logs = read(tmp_path, leaf)
    assert len(logs.flights) == 2 and logs.dt == pytest.approx(0.01)
    assert logs.channels[:6] == ["p_x", "p_y", "p_z", "e_x", "e_y", "e_z"]
    head = pd.read_csv(tmp_path / "flight_000.csv").columns.tolist()
    assert head[:5] == ["t", "u0", "u1", "u2", "u3"] and "s_dot3" in head
    assert channel_names(2, 2) == ["p_x", "p_y", "e", "s0", "s1", "p_dot_x", "p_dot_y", "e_dot", "s_dot0", "s_dot1"]


def _edit(folder, fn):
    path = folder / "flight_001.csv"
    fn(pd.read_csv(path)).to_csv(path, index=False)
    return path


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.drop(columns=["p_y"]), ["flight_001.csv", "p_y"]),
    (lambda t: t.rename(columns={"e_dot_z": "edot_z"}), ["flight_001.csv", "e_dot_z", "edot_z", "misnamed"]),
    (lambda t: t.assign(s2=np.where(np.arange(len(t)) == 7, np.nan, t["s2"])), ["flight_001.csv", "'s2'", "NaN", "row 8"]),
    (lambda t: t.assign(t=t["t"].to_numpy()[::-1]), ["flight_001.csv", "'t'", "increasing"]),
])
def test_bad_columns_are_named(tmp_path, leaf, edit, words):
    fake_logs(tmp_path, leaf)
    _edit(tmp_path, edit)
    with pytest.raises(UserError) as err:
        read(tmp_path, leaf)
    for w in words:
        assert w in str(err.value)


def test_wrong_drone_and_missing_meta(tmp_path, leaf):
    fake_logs(tmp_path, leaf)
    meta = json.loads((tmp_path / "meta.json").read_text())
    meta["drone"] = "rod"
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="meta.json.*'rod'.*'leaf'"):
        read(tmp_path, leaf)
    (tmp_path / "meta.json").unlink()
    with pytest.raises(UserError, match="meta.json: missing"):
        read(tmp_path, leaf)


def test_bad_input_overwrites_nothing(tmp_path, leaf, small_cfg):
    logs, out = tmp_path / "logs", tmp_path / "out"
    out.mkdir()
    (out / "report.json").write_text("earlier report")
    fake_logs(logs, leaf, flights=1)
    q = small_cfg.discrepancy
    with pytest.raises(UserError, match="1 flight.*at least 2"):
        run_workflow(leaf, small_cfg.drone, small_cfg.sim, small_cfg.noise, q, logs, out, small_cfg.cache_dir)
    shutil.rmtree(logs)
    fake_logs(logs, leaf, flights=2)
    _edit(logs, lambda t: t.drop(columns=["u2"]))
    with pytest.raises(UserError, match="flight_001.csv.*u2"):
        run_workflow(leaf, small_cfg.drone, small_cfg.sim, small_cfg.noise, q, logs, out, small_cfg.cache_dir)
    assert (out / "report.json").read_text() == "earlier report"
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
