"""The start-state estimate of the prediction windows: a causal average of the noisy positions
and angles, each carried to the start by the integral of its measured rate."""
import numpy as np

from sdexp.discrepancy.logs import angle_columns, channel_names
from sdexp.discrepancy.windows import make_windows, preceding, start_estimate, subset, thin


def motion(t):
    """(p_x, p_y, e, s0) and their rates: a swing, an accelerating climb, a yaw that crosses
    +-pi, a bend oscillating at 4 Hz (faster than the averaging window)."""
    w = 2 * np.pi * 4
    q = np.c_[np.sin(3 * t), 2 * t + 0.5 * t ** 2, (np.pi - 0.5 + 1.0 * t + np.pi) % (2 * np.pi) - np.pi,
              0.2 * np.sin(w * t)]
    dq = np.c_[3 * np.cos(3 * t), 2 + t, np.ones_like(t), 0.2 * w * np.cos(w * t)]
    return q, dq


def test_the_start_estimate_shrinks_the_noise_without_lag():
    t = np.arange(300) * 0.01
    q, dq = motion(t)
    rng = np.random.default_rng(0)
    sigma = 0.01
    y = np.c_[q + rng.normal(0, sigma, q.shape), dq]
    ang = angle_columns(channel_names(2, 1))
    assert ang[2] and ang.sum() == 1
    rows = np.arange(20, 300)
    raw = start_estimate(t, y, rows, 1, ang)
    np.testing.assert_array_equal(raw, y[rows])
    est = start_estimate(t, y, rows, 8, ang)
    err = est[:, :4] - q[rows]
    err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
    # 1/sqrt(8) of the noise, and no lag: the bias is far below the noise even on the 4 Hz bend
    assert np.sqrt(np.mean(err ** 2)) < 0.45 * sigma
    assert np.abs(err.mean(axis=0)).max() < 0.15 * sigma
    np.testing.assert_array_equal(est[:, 4:], y[rows, 4:])
    # noise-free: the trapezoid rule is exact on the climb and the yaw; on the swing and the
    # bend its error is j dt^3 w^3 A / 12 for a carry over j rows (bend: 2.6e-4 per row)
    exact = start_estimate(t, np.c_[q, dq], rows, 8, ang)[:, :4] - q[rows]
    exact[:, 2] = (exact[:, 2] + np.pi) % (2 * np.pi) - np.pi
    bound = np.array([27, 0, 0, 0.2 * (2 * np.pi * 4) ** 3]) * 1e-6 / 12 * 3.5
    assert np.all(np.abs(exact).max(axis=0) <= 1.05 * bound + 1e-12)


def test_each_window_has_a_predecessor_that_ends_where_it_starts():
    from types import SimpleNamespace
    t = np.arange(300) * 0.01
    q, dq = motion(t)
    flights = [SimpleNamespace(t=t, y=np.c_[q, dq] + k, u=np.c_[t, -t] + k) for k in range(2)]
    w = make_windows(flights, channel_names(2, 1), horizon=20, stride=50, history=30, average=8)
    assert (w.stride, w.average) == (50, 8)
    before = preceding(w)
    assert before.count == w.count and (before.flight_of == w.flight_of).all()
    for s, b in zip(w.starts, before.starts):
        np.testing.assert_array_equal(b, s - 20)
    # the predecessor's last measured row is the window's start row: it never reads the window's data
    np.testing.assert_array_equal(before.measured[:, -1], np.concatenate([f.y[s] for f, s in zip(flights, w.starts)]))
    # subsets keep what the predecessors need
    one = thin(subset(w, [1]), 3)
    assert (one.stride, one.average, one.count) == (50, 8, 3) and (preceding(one).flight_of == 0).all()


def test_a_body_changed_by_its_effect_is_posed_with_its_own_bend_map(small_cfg, leaf, tmp_path):
    """Logs of a heavy payload, noise-free, replayed by the simulator with that very payload: the
    windows posed with the payload-carrying body's bend map predict them better than with the
    nominal body's (whose unseen sag is another body's)."""
    from dataclasses import replace

    from sdexp.config import NoiseConfig
    from sdexp.discrepancy.logs import read_logs
    from sdexp.discrepancy.predict import model_effects
    from sdexp.discrepancy.record import record_flights
    from sdexp.discrepancy.windows import Predictor, make_windows
    from sdexp.discrepancy.workflow import prepare, steps_of

    cfg = small_cfg
    payload = [{"name": "payload", "mass": 0.3, "point": (leaf.fem.rest.mean(axis=0) + [0.4, 0.0, 0.3]).tolist()}]
    assert model_effects(payload + [{"name": "thrust_loss", "rotor": 0, "fraction": 0.2}]) == payload
    quiet = NoiseConfig(enabled=False)
    rec = cfg.discrepancy.record
    record_flights(leaf, cfg.sim, quiet, tmp_path, 2, 2.0, rec.manoeuvres, 3, rec.height, rec.ground, rec.amplitude,
                   effects=payload)
    logs = read_logs(tmp_path, leaf.name, leaf.num_rotors, leaf.layout.n_s, leaf.dim)
    h, stride, hist = steps_of(cfg.discrepancy, logs.dt, float(cfg.discrepancy.history))
    w = make_windows(logs.flights, logs.channels, h, stride, hist)
    bend, _, _, bend_for = prepare(leaf, cfg.drone, cfg.sim, cfg.noise, cfg.discrepancy, cfg.cache_dir)
    nominal_map = np.mean(Predictor(leaf, cfg.sim, quiet, bend).residual(w, payload) ** 2)
    own_map = np.mean(Predictor(leaf, cfg.sim, quiet, bend, bend_for).residual(w, payload) ** 2)
    # (measured: 0.0018 against 0.024)
    assert own_map < 0.5 * nominal_map, (own_map, nominal_map)
    # without a model effect the nominal map is the one used
    r = Predictor(leaf, cfg.sim, quiet, bend, lambda e: (_ for _ in ()).throw(AssertionError(e))).residual(w, [])
    assert np.isfinite(r).all()
