"""data.aggregation: ours' own flights join the random holds in rounds (shrunk: the rod's 800
transitions, two flights of 0.3 s a round)."""
import numpy as np
import pytest

from sdexp.config import validate
from sdexp.errors import UserError
from sdexp.eval.flights import Setup
from tests.conftest import make_cfg, make_config
from tests.eval.references import SHRUNK


def _cfg(cache_dir, *extra):
    return make_config(*SHRUNK, f"cache_dir={cache_dir}", "data.aggregation.flights=2",
                       "data.aggregation.seconds=0.3", *extra)


def test_rounds_add_ours_flights_to_the_holds_and_retrain(cache_dir):
    base = Setup(_cfg(cache_dir), progress=False)
    agg = Setup(_cfg(cache_dir, "data.aggregation.rounds=2"), progress=False)
    n0, n = len(base.data), len(agg.data)
    # two rounds of two flights of up to 30 steps, after the same random holds
    assert n0 < n <= n0 + 2 * 2 * 30
    for k in base.data.arrays:
        np.testing.assert_array_equal(agg.data.arrays[k][:n0], base.data.arrays[k])
    new = agg.data.arrays["episode"][n0:]
    assert new.min() > base.data.arrays["episode"].max() and len(np.unique(new)) <= 4
    # the flights' commands are ours', within the rotors' range; the nets are trained again
    assert np.abs(agg.data.arrays["u"][n0:]).max() <= agg.drone.max_thrust
    assert agg.trained.key != base.trained.key
    # a round is cached: the same transitions, not flown again
    again = Setup(_cfg(cache_dir, "data.aggregation.rounds=2"), progress=False)
    np.testing.assert_array_equal(again.data.arrays["p"], agg.data.arrays["p"])
    # the random holds' cache is the same with and without aggregation
    assert agg.data.meta.get("cached") and len(agg.data.meta["joined"]) == 2
    assert agg.data.meta["joined"][0].startswith("round 1 (") and "transitions" in agg.data.meta["joined"][0]


@pytest.mark.parametrize("override, words", [
    ("data.aggregation.rounds=11", ["data.aggregation.rounds", "[0, 10]"]),
    ("data.aggregation.flights=0", ["data.aggregation.flights", "[1, 1000]"]),
    ("data.aggregation.seconds=-1", ["data.aggregation.seconds"]),
])
def test_an_aggregation_out_of_range_names_the_key_and_its_range(cache_dir, override, words):
    with pytest.raises(UserError) as err:
        validate(make_cfg(*SHRUNK, f"cache_dir={cache_dir}", override))
    for w in words:
        assert w in str(err.value), str(err.value)


def test_a_round_whose_flights_all_fail_at_once_is_logged_and_the_rounds_go_on(cache_dir, monkeypatch, caplog):
    from collections import Counter

    from sdexp.eval import aggregation
    base = Setup(_cfg(cache_dir), progress=False)
    empty = {k: v[:0] for k, v in base.data.arrays.items()}
    monkeypatch.setattr(aggregation, "round_transitions",
                        lambda *a, **k: (dict(empty), Counter({"inverted_element": 2})))
    cfg = _cfg(cache_dir, "data.aggregation.rounds=2")
    with caplog.at_level("WARNING"):
        data, trained, _ = aggregation.aggregate(cfg, base.data, base.trained, base.dyn, progress=False)
    assert len(data) == len(base.data) and trained.key == base.trained.key
    assert sum("every flight failed before its first transition (inverted_element)" in r.message
               for r in caplog.records) == 2
