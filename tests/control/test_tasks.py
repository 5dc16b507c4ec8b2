"""Task goals over time and the angle wrap every controller uses."""
import numpy as np
import pytest

from sdexp.control.tasks import Task, wrap_angle


def test_wrap_angle_maps_into_the_half_open_interval():
    a = np.array([0.0, 0.3, -0.3, np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 2 * np.pi, 7.0, -7.0, 100.0])
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    # the same angle: differs by a whole number of turns
    turns = (a - w) / (2 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-12)
    np.testing.assert_allclose(w[:3], [0.0, 0.3, -0.3], atol=1e-15)
    # +-pi (and odd multiples) land on +pi, never -pi
    np.testing.assert_allclose(w[3:7], np.pi, rtol=1e-15)
    assert w[7] == pytest.approx(0.0, abs=1e-15)
    assert w[8] == pytest.approx(7.0 - 2 * np.pi) and w[9] == pytest.approx(2 * np.pi - 7.0)
    # an error of 350 degrees is a -10 degree error
    assert wrap_angle(np.deg2rad(350.0)) == pytest.approx(np.deg2rad(-10.0))
    assert np.shape(wrap_angle(0.5)) == ()


def test_hover_and_target_goals():
    t = Task(start=[0.0, 1.0, 0.0], target=[2.0, 3.0, -1.0], seconds=5.0, n_s=4)
    for time in (0.0, 1.7, 5.0):
        g = t.goal(time)
        np.testing.assert_array_equal(g.p, [2.0, 3.0, -1.0])
        np.testing.assert_array_equal(g.p_dot, 0.0)
        np.testing.assert_array_equal(g.e, np.zeros(3))
        np.testing.assert_array_equal(g.s, np.zeros(4))
        # the state vector layout (s, s_dot, e, e_dot, p, p_dot)
        assert g.x.shape == (4 + 4 + 3 + 3 + 3 + 3,)
        np.testing.assert_array_equal(g.x[14:17], [2.0, 3.0, -1.0])
    # 2D: one attitude angle
    g2 = Task(start=[0.0, 0.0], target=[1.0, 1.0], seconds=1.0, n_s=2).goal(0.3)
    assert g2.e.shape == (1,) and g2.x.shape == (2 + 2 + 1 + 1 + 2 + 2,)


def test_velocity_tracking_moves_the_goal():
    v = np.array([0.5, 0.0, -0.25])
    t = Task(start=np.zeros(3), target=[1.0, 2.0, 3.0], seconds=10.0, n_s=0, velocity=v)
    for time in (0.0, 0.01, 3.0, 10.0):
        g = t.goal(time)
        np.testing.assert_allclose(g.p, np.array([1.0, 2.0, 3.0]) + v * time, rtol=1e-15)
        np.testing.assert_array_equal(g.p_dot, v)
    # the goal velocity is the derivative of the goal position
    h = 1e-3
    np.testing.assert_allclose((t.goal(2.0 + h).p - t.goal(2.0 - h).p) / (2 * h), v, rtol=1e-9)


def test_bend_keyframes_interpolate_linearly_and_hold_at_the_ends():
    times = [1.0, 2.0, 4.0]
    targets = [[0.0, 0.0], [0.4, -0.2], [0.1, 0.3]]
    t = Task(start=[0.0, 0.0], target=[0.0, 0.0], seconds=5.0, n_s=2, bend_times=times, bend_targets=targets)
    np.testing.assert_allclose(t.goal(0.0).s, [0.0, 0.0])          # before the first keyframe: its value
    np.testing.assert_allclose(t.goal(1.5).s, [0.2, -0.1])         # half way 1 -> 2
    np.testing.assert_allclose(t.goal(2.0).s, [0.4, -0.2])
    np.testing.assert_allclose(t.goal(3.0).s, [0.25, 0.05])        # half way 2 -> 4
    np.testing.assert_allclose(t.goal(3.5).s, [0.4 + 0.75 * (0.1 - 0.4), -0.2 + 0.75 * 0.5])
    np.testing.assert_allclose(t.goal(4.0).s, [0.1, 0.3])
    np.testing.assert_allclose(t.goal(9.0).s, [0.1, 0.3])          # after the last: held
    np.testing.assert_array_equal(t.goal(3.0).s_dot, [0.0, 0.0])
    # without keyframes the goal shape is the rest shape
    np.testing.assert_array_equal(Task([0.0, 0.0], [0.0, 0.0], 1.0, 3).goal(0.5).s, np.zeros(3))


def test_bend_keyframes_must_match_the_times():
    with pytest.raises(ValueError):
        Task([0.0, 0.0], [0.0, 0.0], 1.0, 2, bend_times=[0.0, 1.0], bend_targets=[[0.1, 0.2]])


def test_a_drone_without_peripheral_sensors_has_tasks_too():
    """n_s = 0 (LearnedDynamics supports it): the s blocks are empty."""
    t = Task(start=np.zeros(3), target=np.ones(3), seconds=1.0, n_s=0)
    g = t.goal(0.5)
    assert g.s.shape == (0,) and g.s_dot.shape == (0,)
    assert g.x.shape == (12,)
    np.testing.assert_array_equal(g.x[6:9], np.ones(3))


def test_start_is_copied_as_float_and_velocity_defaults_to_rest():
    t = Task(start=[1, 2], target=[3, 4], seconds=1.0, n_s=0)
    assert t.start.dtype == float and t.target.dtype == float and t.dim == 2
    np.testing.assert_array_equal(t.velocity, [0.0, 0.0])
    # the goal's velocity is a copy: a controller writing into it cannot move the task
    g = t.goal(0.0)
    g.p_dot += 1.0
    np.testing.assert_array_equal(t.goal(0.0).p_dot, [0.0, 0.0])


def test_attitude_goal_defaults_to_level():
    assert not Task(np.zeros(3), np.zeros(3), 1.0, 0).goal(0.2).e.any()
    t = Task(np.zeros(3), np.zeros(3), 1.0, 0, attitude=[0.1, -0.2, 0.3])
    np.testing.assert_array_equal(t.goal(0.2).e, [0.1, -0.2, 0.3])
    np.testing.assert_array_equal(t.goal(0.2).e_dot, np.zeros(3))


def test_a_velocity_ramp_reaches_the_velocity_smoothly_and_keeps_the_position_continuous():
    v = np.array([0.5, 0.0, 0.0])
    t = Task(start=np.zeros(3), target=np.zeros(3), seconds=12.0, n_s=2, velocity=v, ramp=2.0)
    np.testing.assert_allclose(t.goal(0.0).p_dot, 0.0)
    np.testing.assert_allclose(t.goal(1.0).p_dot, 0.5 * v)          # halfway up the ramp
    np.testing.assert_allclose(t.goal(1.0).p, v * 0.25)              # v t^2 / (2 ramp)
    np.testing.assert_allclose(t.goal(2.0).p, v * 1.0)               # continuous at the ramp's end
    np.testing.assert_allclose(t.goal(12.0).p, v * 11.0)             # then v t, 1 s behind
    np.testing.assert_allclose(t.goal(12.0).p_dot, v)
    # the finite difference of the goal position is its velocity, on and after the ramp
    for time in (0.7, 1.9, 5.0):
        fd = (t.goal(time + 1e-6).p - t.goal(time - 1e-6).p) / 2e-6
        np.testing.assert_allclose(fd, t.goal(time).p_dot, atol=1e-6)
    # without a ramp the goal moves at v from the start, as before
    np.testing.assert_allclose(Task(np.zeros(3), np.zeros(3), 5.0, 2, velocity=v).goal(3.0).p, 3 * v)
    with pytest.raises(ValueError, match="ramp"):
        Task(np.zeros(3), np.zeros(3), 5.0, 2, velocity=v, ramp=-1.0)
