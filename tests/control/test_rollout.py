"""fly() and metrics() on the simulated 2D rod with scripted controllers: what the flight
records, how it ends, and the metrics recomputed by hand from the recorded flight."""
from dataclasses import replace

import numpy as np
import pytest

from sdexp.control.lqr import LqrFailure
from sdexp.control.rollout import fly, metrics
from sdexp.control.tasks import Task, wrap_angle
from sdexp.sim.drone import build_drone
from sdexp.sim.simulator import Simulator
from tests.conftest import make_config as make_cfg

DT = 0.01


@pytest.fixture(scope="module")
def rod(cache_dir):
    cfg = make_cfg("drone=rod", f"cache_dir={cache_dir}")
    return cfg, build_drone(cfg.drone, cache_dir, cfg.sim.element)


def simulator(rod, **sim):
    cfg, drone = rod
    return Simulator(drone, replace(cfg.sim, **sim), cfg.noise, seed=3)


def quiet(rod):
    cfg, drone = rod
    return Simulator(drone, cfg.sim, replace(cfg.noise, enabled=False))


class Scripted:
    """Returns ``script(k)`` at the k-th call and records what it was given."""
    name = "scripted"

    def __init__(self, script):
        self.script, self.seen, self.resets = script, [], 0

    def reset(self, task):
        self.resets += 1
        self.k = 0

    def act(self, t, state):
        self.seen.append((t, state.x.copy()))
        self.k += 1
        return self.script(self.k - 1)


def slices(drone):
    n_s = drone.layout.n_s
    e = slice(2 * n_s, 2 * n_s + 1)
    return slice(2 * n_s + 2, 2 * n_s + 4), e


def by_hand(flight, task, p, e, seconds):
    """The README's metrics, straight from the recorded arrays."""
    X, U, T = np.array(flight.x), np.array(flight.u).reshape(-1, 5), np.array(flight.t)
    goals = np.array([task.goal(t).p for t in T])
    err = np.linalg.norm(X[:, p] - goals, axis=1)
    survival = flight.failure_time if flight.failure else seconds
    usage = float(np.abs(U).sum())
    return dict(survival_time=survival, final_error=err[-1], thrust_usage=usage,
                thrust_per_second=usage / survival if survival > 0 else None,
                mean_error_last_5s=err[T >= T[-1] - 5.0].mean(),
                max_attitude_deg=np.rad2deg(np.abs(wrap_angle(X[:, e])).max()),
                max_tilt_deg=np.rad2deg(np.abs(wrap_angle(X[:, e])).max()))   # 2D: tilt = |theta|


def test_release_record_and_metrics_of_a_full_flight(rod):
    cfg, drone = rod
    sim = simulator(rod)
    p, e = slices(drone)
    task = Task(start=[1.0, 5.0], target=[2.0, 4.0], seconds=0.3, n_s=drone.layout.n_s, velocity=[0.5, 0.0])
    ctl = Scripted(lambda k: np.array([3.0, 3.0, 3.0, 3.0, 50.0]))
    calls = []
    flight = fly(sim, ctl, task, on_step=lambda: calls.append(1))
    assert flight.failure is None and flight.controller == "scripted" and ctl.resets == 1
    # released at rest where the measured position is the task's start
    np.testing.assert_allclose(flight.x[0][p], task.start, atol=1e-12)
    assert np.abs(flight.x[0][p.stop:]).max() < 1e-12          # p_dot
    # one command, time and state per control step; commands clipped to max_thrust
    assert len(flight.u) == 30 == len(calls) and len(flight.x) == len(flight.t) == len(flight.goal) == 31
    np.testing.assert_allclose(flight.t, DT * np.arange(31), atol=1e-12)
    np.testing.assert_allclose([t for t, _ in ctl.seen], DT * np.arange(30), atol=1e-12)
    np.testing.assert_array_equal(np.array(flight.u), np.tile([3.0, 3.0, 3.0, 3.0, 10.0], (30, 1)))
    for t, g in zip(flight.t, flight.goal):
        np.testing.assert_allclose(g, task.goal(t).x)
    # the recorded state is the simulator's noise-free one
    np.testing.assert_array_equal(flight.x[-1], sim.state(noisy=False).x)
    m = metrics(flight, p, e, task.seconds)
    want = by_hand(flight, task, p, e, task.seconds)
    assert m["survived"] and m["failure"] == ""
    assert m["survival_time"] == 0.3
    assert m["thrust_usage"] == pytest.approx(30 * 22.0, rel=1e-12) == want["thrust_usage"]
    for k in ("final_error", "thrust_per_second", "mean_error_last_5s", "max_attitude_deg", "max_tilt_deg"):
        assert m[k] == pytest.approx(want[k], rel=1e-12), k
    # the goal moved 0.15 m in x while the rod rose: the error is not the start's distance
    assert m["final_error"] != pytest.approx(np.linalg.norm(task.target - task.start), rel=1e-3)


def test_noise_free_flight_is_what_the_controller_saw_and_obeys_newton(rod):
    cfg, drone = rod
    sim = quiet(rod)
    p, e = slices(drone)
    task = Task(start=[0.0, 0.0], target=[0.0, 0.0], seconds=0.03, n_s=drone.layout.n_s)
    total = 15.0
    ctl = Scripted(lambda k: np.full(5, total / 5))
    flight = fly(sim, ctl, task)
    # no noise, no delay: the state handed to the controller at step k is the recorded one
    assert len(ctl.seen) == 3
    for (t, x), rec in zip(ctl.seen, flight.x[:-1]):
        np.testing.assert_array_equal(x, rec)
    # the commanded thrust is what the body got: 15 N up on 1 kg under gravity and
    # mass-proportional damping c moves the centre of mass by v' = F/m - g - c v (the IMUs,
    # between the rotors of this very soft rod, lag behind: p_dot is not the COM velocity)
    M = drone.fem.mass.sum()
    c, a = drone.damping, total / M - 9.81
    v_expect = a / c * (1 - np.exp(-c * 0.03)) if c > 0 else a * 0.03
    v_com = drone.fem.mass @ sim.v / M
    assert v_com[1] == pytest.approx(v_expect, rel=0.02)
    assert abs(v_com[0]) < 1e-3 * v_expect                    # symmetric: no sideways push


def test_a_controller_lqr_failure_ends_the_flight_as_a_record(rod):
    cfg, drone = rod
    sim = simulator(rod)
    p, e = slices(drone)

    def script(k):
        if k == 5:
            raise LqrFailure("no stabilising solution")
        return np.full(5, 2.0)

    task = Task(start=[0.0, 1.0], target=[0.0, 1.0], seconds=1.0, n_s=drone.layout.n_s)
    flight = fly(sim, Scripted(script), task)
    assert flight.failure.startswith("controller:") and "no stabilising solution" in flight.failure
    assert flight.failure_time == pytest.approx(0.05)
    assert len(flight.u) == 5 and len(flight.x) == 6
    m = metrics(flight, p, e, task.seconds)
    want = by_hand(flight, task, p, e, task.seconds)
    assert not m["survived"] and m["failure"] == flight.failure
    assert m["survival_time"] == pytest.approx(0.05)
    assert m["thrust_usage"] == pytest.approx(5 * 10.0)
    assert m["thrust_per_second"] == pytest.approx(50.0 / 0.05)
    assert m["final_error"] == pytest.approx(want["final_error"], rel=1e-12)


def test_a_non_finite_command_at_the_first_step(rod):
    cfg, drone = rod
    sim = simulator(rod)
    p, e = slices(drone)
    task = Task(start=[0.0, 1.0], target=[3.0, 5.0], seconds=1.0, n_s=drone.layout.n_s)
    flight = fly(sim, Scripted(lambda k: np.array([1.0, np.nan, 1.0, 1.0, 1.0])), task)
    assert flight.failure == "controller: non-finite command" and flight.failure_time == 0.0
    assert flight.u == [] and len(flight.x) == 1
    m = metrics(flight, p, e, task.seconds)
    assert m["survival_time"] == 0.0 and m["thrust_usage"] == 0.0 and not m["survived"]
    assert m["final_error"] == pytest.approx(5.0, rel=1e-9)            # |(3, 5) - (0, 1)|
    assert np.isfinite(m["thrust_per_second"])


def test_a_simulator_blow_up_ends_the_flight_with_its_reason(rod):
    cfg, drone = rod
    sim = simulator(rod, max_speed=0.3)        # free fall passes 0.3 m/s after ~3 steps
    p, e = slices(drone)
    task = Task(start=[0.0, 0.0], target=[0.0, 0.0], seconds=1.0, n_s=drone.layout.n_s)
    flight = fly(sim, Scripted(lambda k: np.zeros(5)), task)
    assert flight.failure.startswith("simulator: runaway_speed")
    assert flight.failure_time == pytest.approx(sim.failure.time)
    steps = int(round(flight.failure_time / DT))
    assert 2 <= steps <= 6
    assert len(flight.u) == steps - 1                            # the failing step is not recorded
    assert flight.t[-1] == pytest.approx(flight.failure_time - DT)
    m = metrics(flight, p, e, task.seconds)
    assert m["survival_time"] == pytest.approx(flight.failure_time) and not m["survived"]
    assert m["thrust_usage"] == 0.0
