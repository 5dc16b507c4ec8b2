"""One candidate protocol for library and user effects: declarations, physical bounds, the
history a slow candidate needs, and a user's own effect named from logs."""
from dataclasses import replace

import numpy as np
import pytest

from sdexp.discrepancy.candidates import candidate, history_seconds, library_candidates
from sdexp.discrepancy.fit import Fit, decide, off_nominal
from sdexp.errors import UserError
from sdexp.sim.physics.effects import LIBRARY, Effect
from tests.discrepancy.test_workflow import record, workflow


class Undeclared(Effect):
    name = "undeclared"

    def __init__(self, k: float = 0.0):
        self.k = k


class OffZero(Undeclared):
    fit_params = {"k": (0.1, 1.0, 0.1)}


def test_every_library_effect_declares_its_fit_and_builds_entries_the_simulator_takes(leaf):
    from sdexp.sim.physics.effects import build_effects
    cands = library_candidates(leaf)
    assert sorted(c.name for c in cands) == sorted(LIBRARY)
    for c in cands:
        assert np.all(c.lower <= 0) and np.all(c.upper >= 0) and np.all(c.lower < c.upper)
        mid = np.clip(c.steps, c.lower, c.upper)
        build_effects(c.build(mid, c.options[0]))     # a fitted value is a valid effect


def test_physical_bounds_flag_a_fit_that_needs_more_than_physics_allows(leaf):
    drag = candidate("quadratic_drag", leaf)
    assert drag.lower[0] == 0.0                        # no negative drag
    assert drag.flags(np.array([0.0]), None) == []     # nominal: on a zero bound, not a flag
    assert "at its upper bound" in drag.flags(drag.upper.copy(), None)[0]
    bias = candidate("imu_bias", leaf)
    assert bias.upper[0] <= 0.1                         # a tilt an accelerometer can be off by
    pay = candidate("payload", leaf)
    assert pay.flags(np.array([0.2, 0.0, 0.0]), None) == []
    far = np.array([0.2, 0.2 * 5.0, 0.0])               # 5 m from the centre: off the 2.4 m leaf
    assert any("not over the body" in f for f in pay.flags(far, None))


def test_a_flagged_fit_does_not_pass_however_much_it_helps():
    held_nominal = np.full(40, 2.0)
    good = Fit("a", None, np.array([0.1]), np.zeros(1), {}, [], 0.0, refined=True,
               held_w=np.full(40, 1.0) + np.linspace(0, 0.01, 40), held_loss=1.0)
    bound = Fit("b", None, np.array([5.0]), np.zeros(1), {}, [], 0.0, refined=True,
                held_w=np.full(40, 0.5) + np.linspace(0, 0.01, 40), held_loss=0.5, flags=["k at its upper bound 5"])
    verdict, best, ties, rows, _ = decide([good, bound], held_nominal, 2, 0.05, 0.02)
    assert best is good and verdict == "effect"
    row = next(r for r in rows if r["candidate"] == "b")
    assert not row["passes"] and row["not_physical"] == ["k at its upper bound 5"]


def test_a_second_effect_must_differ_from_nominal_by_more_than_its_uncertainty():
    held_nominal = np.full(40, 2.0)
    rng = np.random.default_rng(0)
    held = lambda: np.full(40, 1.0) + np.linspace(0, 0.01, 40)  # noqa: E731  (both help the held-out windows alike)
    # theta -0.59, its flight bootstrap from about -1.4 to +0.3: the interval holds the nominal 0
    vague = Fit("damping_scale", None, np.array([-0.59]), np.array([0.4]), {}, [], 0.0, refined=True,
                held_w=held(), held_loss=1.0, spread=rng.normal(0, 0.45, (100, 1)))
    # theta 0.22, spread 0.07: the interval excludes 0
    clear = Fit("payload", None, np.array([0.22]), np.array([0.07]), {}, [], 0.0, refined=True,
                held_w=held() + 0.001, held_loss=1.001, spread=rng.normal(0, 0.07, (100, 1)))
    assert not off_nominal(vague) and off_nominal(clear)
    # the first effect: the held-out test alone, and the vague fit wins
    _, best, _, _, _ = decide([vague, clear], held_nominal, 2, 0.05, 0.02)
    assert best is vague
    # a second effect: the vague fit cannot pass however much it helps
    verdict, best, ties, rows, _ = decide([vague, clear], held_nominal, 2, 0.05, 0.02, need_off_nominal=True)
    assert best is clear and verdict == "effect" and ties == []
    row = next(r for r in rows if r["candidate"] == "damping_scale")
    assert not row["passes"] and row["off_nominal"] is False
    _, best, _, _, _ = decide([vague], held_nominal, 1, 0.05, 0.02, need_off_nominal=True)
    assert best is None


def test_user_effects_are_candidates_by_target_and_errors_name_the_fix(leaf):
    tilt = candidate({"_target_": "sdexp.discrepancy.bench_effects.RotorTilt", "rotor": 1}, leaf)
    assert tilt.name == "rotor_tilt" and tilt.params == ["angle"]
    assert tilt.build(np.array([0.1]), None) == [{"_target_": "sdexp.discrepancy.bench_effects.RotorTilt",
                                                  "rotor": 1, "angle": 0.1}]
    assert tilt.base(None)[0]["angle"] == 0.0          # the reference is the effect at theta = 0
    with pytest.raises(UserError, match="fit_params"):
        candidate({"_target_": "tests.discrepancy.test_candidates.Undeclared"}, leaf)
    with pytest.raises(UserError, match="choose one of"):
        candidate("motor_lagg", leaf)
    with pytest.raises(UserError, match="cannot be imported"):
        candidate({"_target_": "nowhere.Effect"}, leaf)
    with pytest.raises(UserError, match="is not an sdexp.sim.physics.effects.Effect"):
        candidate({"_target_": "collections.OrderedDict"}, leaf)
    with pytest.raises(UserError, match=r"undeclared.k bounds \[0.1, 1.0\] exclude its nominal 0"):
        candidate({"_target_": "tests.discrepancy.test_candidates.OffZero"}, leaf)


def test_windows_replay_several_time_constants_of_the_slowest_lag(leaf):
    lag = candidate("motor_lag", leaf)
    assert history_seconds([lag], 0.3) == pytest.approx(3 * lag.upper[0])
    assert history_seconds([candidate("payload", leaf)], 0.3) == 0.3


def test_a_users_own_hypothesis_is_named_from_the_logs(tmp_path, small_cfg, leaf):
    user = {"_target_": "sdexp.discrepancy.bench_effects.RotorTilt", "rotor": 0}
    cfg = replace(small_cfg, discrepancy=replace(small_cfg.discrepancy, candidates=["motor_lag", "payload", user]))
    record(cfg, leaf, tmp_path / "logs", [{**user, "angle": 0.2}], seed=21)
    rep = workflow(cfg, leaf, tmp_path / "logs", tmp_path / "out")
    assert rep["verdict"] in ("effect", "tie", "partly") and rep["effects"][0]["name"] == "rotor_tilt"
    assert rep["effects"][0]["params"]["angle"] == pytest.approx(0.2, rel=0.5)


class _Windows:
    """Training windows of a synthetic one-channel predictor: 6 flights of 4 windows."""
    count = 24
    flight_of = np.repeat(np.arange(6), 4)


def _profiled(response, truth: float, seed: int = 0):
    """Fit theta of ``response`` (theta -> (24, 50, 1) prediction) to data made at ``truth``
    (flight-level offsets + white noise), profile it, and return (fit, bootstrap-only interval,
    profiled interval) of the reported value."""
    from sdexp.discrepancy.candidates import Candidate
    from sdexp.discrepancy.fit import linear_fit, params_interval, profile
    rng = np.random.default_rng(seed)
    y = response(truth) + 0.3 * rng.normal(size=(6, 1, 1, 1)).repeat(4, 0).reshape(24, 1, 1) \
        + rng.normal(size=(24, 50, 1))

    class Pred:
        def residual(self, windows, effects):
            th = effects[0]["v"] if effects else 0.0
            return y - response(th)

    cand = Candidate("x", ["v"], np.array([0.2]), np.array([0.0]), np.array([2.0]),
                     lambda th, o: [{"v": float(th[0])}], lambda th, o: {"v": float(th[0])})
    sigma = np.ones((50, 1))   # the noise floor per step and channel
    fit = linear_fit(cand, Pred(), _Windows(), sigma, Pred().residual(None, []), [], rng)
    fit.train_loss = float(np.mean(Pred().residual(None, cand.build(fit.theta, None)) ** 2))
    before = params_interval(fit, cand)["v"], fit.theta[0], fit.train_loss
    profile(fit, cand, Pred(), _Windows(), _Windows(), sigma, [])
    return fit, before, params_interval(fit, cand)["v"]


def test_a_profile_widens_an_interval_only_where_the_loss_is_flat():
    a = np.linspace(-1, 1, 50)[None, :, None] * np.ones((24, 1, 1)) * 3.0
    # a response that stops growing past 0.5: data made at 0.8 say "at least about 0.5"; the
    # linear bootstrap, blind to the flat side, gives a narrow interval below the truth
    flat = lambda th: a * (min(th, 0.5) + 0.02 * max(th - 0.5, 0.0))  # noqa: E731
    fit, (before, _, _), after = _profiled(flat, 0.8)
    assert before[1] < 0.8 <= after[1]
    assert after[0] == pytest.approx(before[0])      # the steep side keeps the bootstrap's end
    # a response linear in theta: the profile's edges are the bootstrap's (t/2 on the paired
    # test is the Wald interval there), so the interval and the fit stay
    line = lambda th: a * th  # noqa: E731
    fit, (before, theta, _), after = _profiled(line, 0.4)
    assert before[0] <= 0.4 <= before[1] and after == pytest.approx(before) and fit.theta[0] == theta


def test_a_profile_moves_a_fit_that_stopped_short_to_its_lower_loss():
    # a response that flattens (a square root): the Jacobian from theta = 0 overshoots the
    # slope, and the linear fit stops at about half the truth
    a = np.linspace(-1, 1, 50)[None, :, None] * np.ones((24, 1, 1)) * 3.0
    fit, (before, theta, loss), after = _profiled(lambda th: a * np.sqrt(th), 0.8)
    assert theta < 0.6 and before[1] < 0.8
    assert theta < fit.theta[0] <= 0.8 and fit.train_loss < loss and after[1] > before[1]
    assert fit.held_loss == pytest.approx(fit.train_loss)   # scored again (the same windows here)
