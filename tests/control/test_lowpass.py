"""The state low-pass a controller can read through (sdexp.control.lowpass, control.lowpass):
its response against the closed form, angles taken the short way round, a fresh start every
flight, every controller built alike, and what it is for: the rainbow's rigid LQR, which pumps
the body's 5 Hz mode into a fall with the state as read, holds its hover through the filter."""
import numpy as np
import pytest

from sdexp.control.lowpass import LowPassed
from sdexp.control.rollout import fly
from sdexp.control.tasks import Task
from sdexp.eval.controllers import build
from sdexp.sensing import State
from sdexp.sim.drone import build_drone
from sdexp.sim.simulator import Simulator
from tests.conftest import make_config


class Echo:
    """Returns nothing useful; keeps what it was shown."""
    name = "echo"

    def __init__(self):
        self.seen, self.resets = [], 0

    def reset(self, task):
        self.resets += 1

    def act(self, t, state):
        self.seen.append(state)
        return np.zeros(2)


def state(s=0.0, e=0.0, p=0.0):
    one = np.ones(1)
    return State(s * one, e * one, p * np.ones(2), 0 * one, 0 * one, np.zeros(2))


def test_a_step_is_followed_by_the_first_order_closed_form():
    inner = Echo()
    ctl = LowPassed(inner, tau=0.03, dt=0.01)
    ctl.reset(None)
    ctl.act(0.0, state(p=0.0))            # the first reading is taken as it is
    for _ in range(10):
        ctl.act(0.0, state(p=1.0))
    a = 0.01 / 0.04
    got = np.array([st.p[0] for st in inner.seen[1:]])
    assert np.allclose(got, 1 - (1 - a) ** np.arange(1, 11))
    assert inner.seen[0].p[0] == 0.0 and ctl.name == "echo"


def test_angles_are_filtered_the_short_way_round():
    inner = Echo()
    ctl = LowPassed(inner, tau=0.01, dt=0.01)
    ctl.reset(None)
    ctl.act(0.0, state(e=np.pi - 0.1))
    ctl.act(0.0, state(e=-np.pi + 0.1))   # 0.2 rad further on, across +-pi
    e = inner.seen[-1].e[0]
    assert abs(abs(e) - np.pi) < 1e-9     # half way: on the seam, not through zero


def test_every_flight_starts_from_its_own_first_reading():
    inner = Echo()
    ctl = LowPassed(inner, tau=1.0, dt=0.01)
    ctl.reset(None)
    ctl.act(0.0, state(p=5.0))
    ctl.reset(None)
    ctl.act(0.0, state(p=-2.0))
    assert inner.seen[-1].p[0] == -2.0 and inner.resets == 2


def test_build_wraps_every_controller_alike_only_when_asked(cache_dir):
    cfg = make_config("drone=rod", f"cache_dir={cache_dir}", "control.lowpass=0.02")
    drone = build_drone(cfg.drone, cache_dir, cfg.sim.element)
    for name in ("rigid_lqr", "geometry_lqr"):
        ctl = build(name, cfg, Simulator(drone, cfg.sim, cfg.noise, seed=0))
        assert isinstance(ctl, LowPassed) and ctl.name == name and ctl.tau == 0.02
    plain = make_config("drone=rod", f"cache_dir={cache_dir}")
    assert not isinstance(build("rigid_lqr", plain, Simulator(drone, plain.sim, plain.noise, seed=0)), LowPassed)


@pytest.mark.parametrize("tau", [0.0, 0.03])
def test_the_rainbows_mode_is_left_alone_through_the_filter(cache_dir, tau):
    """Physics, not a setting: the rainbow's frame IMU tilts with the body's 5 Hz mode under a
    differential thrust, and the rigid LQR's rate feedback (30 ms late, the paper's noise)
    pumps that mode until the saturated differential thrust costs the lift: it drops metres
    within 3 s (7.6 m). Through a 30 ms low-pass the same gains hold the hover (6 cm)."""
    cfg = make_config("drone=rainbow", f"cache_dir={cache_dir}", "control=tuned", f"control.lowpass={tau}")
    drone = build_drone(cfg.drone, cache_dir, cfg.sim.element)
    sim = Simulator(drone, cfg.sim, cfg.noise, seed=0)
    task = Task(start=np.zeros(2), target=np.zeros(2), seconds=3.0, n_s=drone.layout.n_s)
    flight = fly(sim, build("rigid_lqr", cfg, sim), task)
    a = flight.arrays()
    sl = slice(2 * drone.layout.n_s + 2, 2 * drone.layout.n_s + 4)   # p in (s, s_dot, e, e_dot, p, p_dot)
    drop = -a["x"][:, sl][:, 1].min()
    if tau == 0:
        assert drop > 1.0
    else:
        assert drop < 0.2 and flight.failure is None
