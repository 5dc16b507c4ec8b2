"""Loss of control (rollout.LossOfControl, config ``flight``): a flight whose body tilts past
flight.max_tilt_deg from upright, or whose measured position strays farther than
flight.arena_margin from the box spanned by the task's start and goals, ends there with the
reason and time recorded like a blow-up; a hovering flight is not cut. Each cut flight is
compared with the same flight flown without limits (noise-free, so bitwise the same up to the
cut), whose crossing is found by hand."""
from dataclasses import replace

import numpy as np
import pytest

from sdexp.config import FlightConfig
from sdexp.control.rollout import arena, fly, metrics, tilt
from sdexp.control.tasks import Task
from sdexp.eval.controllers import build, geometry_of
from sdexp.sim.drone import build_drone
from sdexp.sensing.rotations import matrix_from_euler
from sdexp.sim.simulator import Simulator
from tests.conftest import make_config as make_cfg

NO_LIMITS = FlightConfig(max_tilt_deg=None, arena_margin=None)


@pytest.fixture(scope="module")
def rod(cache_dir):
    cfg = make_cfg("drone=rod", f"cache_dir={cache_dir}")
    return cfg, build_drone(cfg.drone, cache_dir, cfg.sim.element)


@pytest.fixture(scope="module")
def leaf(cache_dir):
    """The coarse leaf of the discrepancy tests (599 tets): a 3D body that flies in ms a step."""
    cfg = make_cfg("drone=leaf", "drone.mesh.edge_length=0.5", "control=tuned", f"cache_dir={cache_dir}")
    return cfg, build_drone(cfg.drone, cache_dir, cfg.sim.element)


class Constant:
    name = "constant"

    def __init__(self, u):
        self.u = np.asarray(u, dtype=float)

    def reset(self, task):
        pass

    def act(self, t, state):
        return self.u


def quiet(model):
    cfg, drone = model
    return Simulator(drone, cfg.sim, replace(cfg.noise, enabled=False))


def blocks(drone):
    """Slices of e and p in the state vector (s, s_dot, e, e_dot, p, p_dot)."""
    n_s, n_e, dim = drone.layout.n_s, drone.layout.n_e, drone.dim
    e0 = 2 * n_s
    return slice(e0, e0 + n_e), slice(e0 + 2 * n_e, e0 + 2 * n_e + dim)


def box_distance(p, lo, hi):
    return np.linalg.norm(np.maximum(0.0, np.maximum(lo - p, p - hi)), axis=-1)


# ------------------------------------------------------------------------------ the measures

def test_tilt_is_the_angle_between_the_body_up_axis_and_world_up():
    rng = np.random.default_rng(0)
    e = rng.uniform(-np.pi, np.pi, (500, 3))
    e[:, 2] /= 2                                               # e_z in [-90, 90] deg, as decompose gives
    up = matrix_from_euler(e)[:, :, 1]                         # the body's Y axis in the world
    want = np.arctan2(np.linalg.norm(np.cross(up, [0.0, 1.0, 0.0]), axis=1), up[:, 1])
    np.testing.assert_allclose(tilt(e), want, atol=1e-9)
    # one angle from all three components: roll and pitch of 170 deg is a yaw of 180 deg and a
    # tilt of 14 deg (a component-wise check would call it upside down); yaw alone never tilts
    d = np.deg2rad
    assert np.rad2deg(tilt(d([170.0, 0.0, 170.0]))) == pytest.approx(np.rad2deg(np.arccos(np.cos(d(170.0)) ** 2)))
    assert np.rad2deg(tilt(d([170.0, 0.0, 170.0]))) < 15
    assert tilt(d([0.0, 123.0, 0.0])) == pytest.approx(0.0, abs=1e-12)
    assert np.rad2deg(tilt(d([0.0, 0.0, 89.0]))) == pytest.approx(89.0)
    assert np.rad2deg(tilt(d([100.0, 30.0, 0.0]))) == pytest.approx(100.0)
    # 2D: the frame angle, wrapped
    np.testing.assert_allclose(tilt(np.array([[2 * np.pi - 0.1], [-2.0], [3.0]])), [0.1, 2.0, 3.0], atol=1e-12)


def test_the_arena_spans_the_start_and_the_goal_path():
    task = Task(start=[1.0, 2.0, 3.0], target=[4.0, 0.0, 3.0], seconds=2.0, n_s=0, velocity=[0.0, 1.0, -2.0])
    lo, hi = arena(task)                                       # goal at the end: (4, 2, -1)
    np.testing.assert_allclose(lo, [1.0, 0.0, -1.0])
    np.testing.assert_allclose(hi, [4.0, 2.0, 3.0])


def test_the_limits_are_validated(rod):
    from sdexp.config import validate
    from sdexp.errors import UserError

    cfg, _ = rod
    validate(cfg)
    assert cfg.flight.max_tilt_deg == 90.0 and cfg.flight.arena_margin == 10.0
    for key, bad in (("max_tilt_deg", 0.0), ("max_tilt_deg", 181.0), ("arena_margin", -1.0)):
        c = replace(cfg, flight=replace(cfg.flight, **{key: bad}))
        with pytest.raises(UserError, match=f"flight.{key}"):
            validate(c)


# ------------------------------------------------------------------------------ flights

def test_a_flip_ends_the_flight_as_loss_of_control_when_the_tilt_passes_90_deg(rod):
    cfg, drone = rod
    e, _ = blocks(drone)
    task = Task(start=[0.0, 2.0], target=[0.0, 2.0], seconds=3.0, n_s=drone.layout.n_s)
    torque = Constant([10.0, 10.0, 0.0, -10.0, -10.0])        # one end up, the other down: it turns over
    free = fly(quiet(rod), torque, task, limits=NO_LIMITS)
    assert free.failure is None and len(free.t) == 301
    deg = np.rad2deg(tilt(np.array(free.x)[:, e]))
    k = int(np.argmax(deg > 90.0))
    assert deg[k] > 90.0 and 10 < k < 250                      # it flips well inside the flight

    flight = fly(quiet(rod), torque, task)                     # the schema's limits: 90 deg, 10 m
    assert flight.failure == f"loss_of_control: tilt {deg[k]:.1f} deg > 90"
    assert flight.failure_time == pytest.approx(free.t[k]) == pytest.approx(flight.t[-1])
    # the same flight up to the step that crossed the limit, which is recorded; nothing after it
    assert len(flight.x) == k + 1 and len(flight.u) == k
    np.testing.assert_array_equal(np.array(flight.x), np.array(free.x)[: k + 1])
    m = metrics(flight, slice(0, 0), e, task.seconds)
    assert not m["survived"] and m["failure"] == flight.failure
    assert m["survival_time"] == pytest.approx(free.t[k])
    assert 90.0 < m["max_tilt_deg"] == pytest.approx(deg[k])

    # the threshold is the config's: at 45 deg the same flight ends earlier, at its first step past 45
    j = int(np.argmax(deg > 45.0))
    assert j < k
    early = fly(quiet(rod), torque, task, limits=FlightConfig(max_tilt_deg=45.0, arena_margin=None))
    assert early.failure == f"loss_of_control: tilt {deg[j]:.1f} deg > 45"
    assert early.failure_time == pytest.approx(free.t[j])


def test_a_3d_flip_is_judged_by_the_frame_imu_up_axis(leaf):
    cfg, drone = leaf
    assert len(drone.layout.frame_idx) == 1
    fi = drone.layout.frame_idx[0]
    sim = quiet(leaf)
    u = np.where(geometry_of(sim, rest=True).rotor_pos[:, 0] > 0, 10.0, 0.0)   # lift on the +x side only
    task = Task(start=[0.0, 0.0, 0.0], target=[0.0, 0.0, 0.0], seconds=3.0, n_s=drone.layout.n_s)
    ups = []    # the angle of the frame IMU's Y axis from world +Y, read straight from the readings

    def record():
        ups.append(np.rad2deg(np.arccos(np.clip(sim.readings(noisy=False).rot[fi][1, 1], -1, 1))))
    flight = fly(sim, Constant(u), task, on_step=record)
    assert flight.failure is not None and flight.failure.startswith("loss_of_control: tilt")
    assert len(ups) == len(flight.u) > 10
    assert ups[-1] > 90.0 and max(ups[:-1]) <= 90.0              # ended at the first step past 90 deg
    assert flight.failure == f"loss_of_control: tilt {ups[-1]:.1f} deg > 90"
    assert flight.failure_time == pytest.approx(flight.t[-1])


def test_drifting_out_of_the_arena_ends_the_flight(rod):
    cfg, drone = rod
    e, p = blocks(drone)
    # free fall from the start; the goal sits 3 m below it: the arena is the segment between
    # them widened by the margin, so a fall of 13 m leaves the schema's 10 m arena
    task = Task(start=[1.0, 0.0], target=[1.0, -3.0], seconds=4.0, n_s=drone.layout.n_s)
    drop = Constant(np.zeros(5))
    free = fly(quiet(rod), drop, task, limits=NO_LIMITS)
    X = np.array(free.x)
    assert np.rad2deg(tilt(X[:, e])).max() < 1.0               # it falls level: no tilt to trip over
    d = box_distance(X[:, p], np.array([1.0, -3.0]), np.array([1.0, 0.0]))
    k = int(np.argmax(d > 10.0))
    assert d[k] > 10.0 and 100 < k < 390
    assert X[k, p][1] < -13.0 < X[k - 1, p][1]                  # 10 m below the goal, not the start

    flight = fly(quiet(rod), drop, task)
    assert flight.failure.startswith(f"loss_of_control: left the arena, {d[k]:.2f} m > 10 m")
    assert flight.failure_time == pytest.approx(free.t[k]) == pytest.approx(flight.t[-1])
    np.testing.assert_array_equal(np.array(flight.x), X[: k + 1])
    m = metrics(flight, p, e, task.seconds)
    assert not m["survived"] and m["survival_time"] == pytest.approx(free.t[k])

    # a 2 m margin: out at the first step more than 2 m from the box
    j = int(np.argmax(d > 2.0))
    near = fly(quiet(rod), drop, task, limits=FlightConfig(max_tilt_deg=90.0, arena_margin=2.0))
    assert near.failure.startswith(f"loss_of_control: left the arena, {d[j]:.2f} m > 2 m")
    assert near.failure_time == pytest.approx(free.t[j])


@pytest.fixture(scope="module")
def stiff_leaf(cache_dir):
    """The coarse leaf ten times stiffer: a body the rigid LQR holds (at its 3 kPa the converged,
    quadratic leaf bends too much for it and falls)."""
    cfg = make_cfg("drone=leaf", "drone.mesh.edge_length=0.5", "drone.youngs_modulus=30000", "control=tuned",
                   f"cache_dir={cache_dir}")
    return cfg, build_drone(cfg.drone, cache_dir, cfg.sim.element)


def test_a_hover_flight_is_not_cut(stiff_leaf):
    """The rigid LQR holds the leaf at a goal far from the origin that moves 4.5 m: the whole
    flight, with the schema's limits and with a 2 m arena (it spans the goal's path)."""
    cfg, drone = stiff_leaf
    e, p = blocks(drone)
    task = Task(start=[20.0, 30.0, -10.0], target=[20.0, 30.0, -10.0], seconds=4.0, n_s=drone.layout.n_s,
                velocity=[1.0, 0.0, 0.5])
    for limits in (None, FlightConfig(max_tilt_deg=90.0, arena_margin=2.0)):
        sim = Simulator(drone, cfg.sim, cfg.noise, seed=3)     # paper noise and delay
        flight = fly(sim, build("rigid_lqr", cfg, sim), task, limits=limits)
        assert flight.failure is None, flight.failure
        assert len(flight.t) == 401
        m = metrics(flight, p, e, task.seconds)
        assert m["survived"] and m["survival_time"] == 4.0 and m["failure"] == ""
        assert 0.5 < m["max_tilt_deg"] < 45.0                  # it flew (and wobbled), upright
        X = np.array(flight.x)
        # an arena around the start alone would have cut it: it followed the goal
        assert np.linalg.norm(X[:, p] - task.start, axis=1).max() > 3.0
        # and ends nearer the goal than half its 4.5 m path (1.84 m behind: a P-type tracker lags a
        # ramp; 0.97 m before 2026-11-26, when the coarse leaf's thrust was shared among patch vertices)
        path = np.linalg.norm(task.goal(4.0).p - task.start)
        assert np.linalg.norm(X[-1, p] - task.goal(4.0).p) < 0.5 * path
