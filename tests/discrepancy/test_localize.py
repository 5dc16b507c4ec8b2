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
