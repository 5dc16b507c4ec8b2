"""The unexplained test works on flights: a consistent 30% excess (below the old 1.5x line) is
named, a flight set as noisy as the floor's is not."""
import numpy as np

from sdexp.discrepancy.localize import channel_excess, unexplained_channels


def flights(rng, n, level, windows=40, horizon=20, channels=3, spread=0.08):
    """Residuals whose per-flight loss is level x (1 + spread N(0,1)) on channel 0, 1 elsewhere."""
    r, of = [], []
    for i in range(n):
        scale = np.ones(channels)
        scale[0] = np.sqrt(level * (1 + spread * rng.normal()))
        r.append(rng.normal(size=(windows, horizon, channels)) * scale)
        of.append(np.full(windows, i))
    return np.concatenate(r), np.concatenate(of)


def verdict(level, seed):
    rng = np.random.default_rng(seed)
    rf, ff = flights(rng, 8, 1.0)
    sigma = np.ones((20, 3))
    names = ["a", "b", "c"]
    held = channel_excess(*flights(rng, 4, level), rf, ff, sigma, names)
    train = channel_excess(*flights(rng, 4, level), rf, ff, sigma, names)
    return unexplained_channels(held, train, 1.2, 0.05)


def test_a_consistent_excess_below_one_and_a_half_is_unexplained():
    # 30% on 4 + 4 flights against 8 floor flights: found in at least 8 of 10 draws (power)
    assert sum(verdict(1.3, s) == ["a"] for s in range(10)) >= 8


def test_flights_like_the_floor_are_not():
    assert sum(bool(verdict(1.0, s)) for s in range(40)) <= 2


def test_the_floor_flight_rule_is_what_the_permutation_test_needs_to_reach_its_level():
    # 4 held-out flights far above the floor on channel a: the test's p there is its smallest,
    # 1 / C(4 + floor, 4); floor_needed's count reaches alpha / channels (28: the flower), one
    # flight fewer does not (the flower's 8 floor flights once made `unexplained` impossible)
    from sdexp.discrepancy.workflow import floor_needed
    alpha, channels = 0.05, 28
    need = floor_needed(4, channels, alpha)
    assert need == 9
    rng = np.random.default_rng(0)

    def smallest_p(floor):
        rf, ff = flights(rng, floor, 1.0)
        return channel_excess(*flights(rng, 4, 50.0), rf, ff, np.ones((20, 3)), ["a", "b", "c"]).p.iloc[0]   # channel a: the excess
    assert smallest_p(need) <= alpha / channels < smallest_p(need - 1)
    assert floor_needed(4, 20, alpha, least=8) == 8 and floor_needed(4, 20, alpha) == 8   # the leaf


def test_floor_flights_null_follows_the_drones_channels_and_a_number_is_kept():
    from types import SimpleNamespace

    from sdexp.discrepancy.workflow import floor_flight_count
    from tests.conftest import make_config
    dcfg = make_config().discrepancy
    flower = SimpleNamespace(dim=3, layout=SimpleNamespace(n_s=8))
    rod = SimpleNamespace(dim=2, layout=SimpleNamespace(n_s=8))
    assert dcfg.floor_flights is None
    assert floor_flight_count(flower, dcfg) == 9 and floor_flight_count(rod, dcfg) == 8
    assert floor_flight_count(flower, make_config("discrepancy.floor_flights=5").discrepancy) == 5
