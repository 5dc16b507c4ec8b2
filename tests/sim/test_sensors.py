"""The sensor pipeline returns known angles on hand-built configurations."""
import numpy as np
import pytest

from sdexp.config import DroneConfig
from sdexp.sim.drone import assemble_drone
from sdexp.sensing.rotations import (average_rotations, euler_from_matrix, euler_rates, matrix_from_euler,
                                 skew)
from sdexp.sensing import decompose
from sdexp.sim.sensors import read_imus
from sdexp.sim.mesh.shape import Shape
from sdexp.sim.mesh.structured import box_tets, box_tris

T = 0.1  # plate thickness


def plate_drone():
    """A 3 m x 0.1 m x 1 m plate with a centre IMU and IMUs at x = -1.2 and x = +1.2."""
    pts, tets = box_tets((30, 1, 10), (3.0, T, 1.0), (-1.5, -T / 2, -0.5))
    up = np.array([0.0, 1.0, 0.0])
    imus = np.array([[-1.2, T / 2, 0.0], [1.2, T / 2, 0.0]])
    shape = Shape(3, np.zeros((0, 3)), np.zeros((0, 3), int), np.zeros((0, 3)), np.zeros(3),
                  rotors=np.array([[-1.4, T / 2, 0], [0, T / 2, 0], [1.4, T / 2, 0]]),
                  rotor_normals=np.tile(up, (3, 1)), imus=imus, imu_normals=np.tile(up, (2, 1)),
                  frame_imus=np.array([[0.0, T / 2, 0.0]]), frame_normals=up[None])
    cfg = DroneConfig(name="plate", shape="test", size=[3.0, T, 1.0], youngs_modulus=1e4,
                      num_rotors=3, num_sensors=2, rotor_radius=0.15, imu_radius=0.15)
    return assemble_drone(cfg, shape, pts, tets, "linear")


def beam_drone_2d():
    pts, tris = box_tris((30, 2), (3.0, T), (-1.5, -T / 2))
    up = np.array([0.0, 1.0])
    shape = Shape(2, np.zeros((0, 2)), np.zeros((0, 2), int), np.zeros((0, 2)), np.zeros(2),
                  rotors=np.array([[-1.4, T / 2], [1.4, T / 2]]), rotor_normals=np.tile(up, (2, 1)),
                  imus=np.array([[-1.2, T / 2], [1.2, T / 2]]), imu_normals=np.tile(up, (2, 1)),
                  frame_imus=np.array([[0.0, T / 2]]), frame_normals=up[None])
    cfg = DroneConfig(name="beam", dim=2, shape="test", size=[3.0, T], youngs_modulus=1e4,
                      num_rotors=2, num_sensors=2, rotor_radius=0.15, imu_radius=0.15)
    return assemble_drone(cfg, shape, pts, tris, "linear")


@pytest.fixture(scope="module")
def plate():
    return plate_drone()


def hinge(x, v, pivot_x, angle, rate, side=1):
    """Fold the part beyond x = pivot_x (side=1) or before -pivot_x (side=-1) up by angle
    about the z axis through the top surface, moving at ``rate`` rad/s."""
    x, v = x.copy(), v.copy()
    sel = side * (x[:, 0] - side * pivot_x) > 0
    pivot = np.array([side * pivot_x, T / 2, 0.0])
    Rz = matrix_from_euler(np.array([0.0, 0.0, side * angle]))
    x[sel] = (x[sel] - pivot) @ Rz.T + pivot
    w = np.array([0.0, 0.0, side * rate])
    v[sel] += np.cross(w, x[sel] - pivot)
    return x, v


def test_rest_reads_zero(plate):
    st = decompose(read_imus(0.0, plate.fem.rest, np.zeros_like(plate.fem.rest), plate.imus), plate.layout)
    assert np.abs(st.s).max() < 1e-12 and np.abs(st.e).max() < 1e-12
    np.testing.assert_allclose(st.p, [0.0, T / 2, 0.0], atol=1e-9)  # IMUs sit on the top face
    assert np.abs(np.r_[st.s_dot, st.e_dot, st.p_dot]).max() < 1e-12


def test_rigid_motion_reads_euler_angles_and_rates(plate):
    e0 = np.array([0.3, -2.1, 0.5])
    R = matrix_from_euler(e0)
    t = np.array([1.0, 2.0, -3.0])
    Om, V = np.array([0.2, -0.4, 0.7]), np.array([0.5, 0.0, -1.0])
    x = plate.fem.rest @ R.T + t
    v = np.cross(Om, x - t) + V
    st = decompose(read_imus(0.0, x, v, plate.imus), plate.layout)
    np.testing.assert_allclose(st.e, e0, atol=1e-9)
    np.testing.assert_allclose(st.s, 0.0, atol=1e-9)
    np.testing.assert_allclose(st.s_dot, 0.0, atol=1e-9)
    np.testing.assert_allclose(st.e_dot, euler_rates(e0, Om), atol=1e-9)
    p_rest = read_imus(0.0, plate.fem.rest, 0 * x, plate.imus).pos.mean(0)
    np.testing.assert_allclose(st.p, R @ p_rest + t, atol=1e-9)


@pytest.mark.parametrize("angle", [-0.6, -0.05, 0.05, 0.4, 1.2])
def test_raised_wing_reads_its_bend_angle(plate, angle):
    """Raising either wing (tip towards +Y) is positive, whatever the side."""
    for side, k in ((1, 1), (-1, 0)):
        x, v = hinge(plate.fem.rest, np.zeros_like(plate.fem.rest), 0.6, angle, 0.8, side)
        st = decompose(read_imus(0.0, x, v, plate.imus), plate.layout)
        assert st.s[k] == pytest.approx(angle, abs=1e-9)
        assert st.s[1 - k] == pytest.approx(0.0, abs=1e-9)
        assert st.s_dot[k] == pytest.approx(0.8, abs=1e-6)
        np.testing.assert_allclose(st.e, 0.0, atol=1e-12)


def test_bend_rate_matches_finite_difference_through_zero(plate):
    """s is smooth through the flat configuration (the sign flips with arccos' kink)."""
    h = 1e-6
    for a in (-1e-3, 0.0, 2e-3):
        xs = [hinge(plate.fem.rest, 0 * plate.fem.rest, 0.6, a + d, 0.0)[0] for d in (-h, h)]
        s = [decompose(read_imus(0, x, 0 * x, plate.imus), plate.layout).s[1] for x in xs]
        x, v = hinge(plate.fem.rest, 0 * plate.fem.rest, 0.6, a, 1.0)
        st = decompose(read_imus(0, x, v, plate.imus), plate.layout)
        assert st.s_dot[1] == pytest.approx((s[1] - s[0]) / (2 * h), rel=1e-4)


def test_bend_is_frame_independent(plate):
    """A bent plate flown at an attitude reads the same s and the attitude."""
    x, v = hinge(plate.fem.rest, np.zeros_like(plate.fem.rest), 0.6, 0.5, 0.0)
    e0 = np.array([-0.4, 1.0, 0.2])
    st = decompose(read_imus(0.0, x @ matrix_from_euler(e0).T, v, plate.imus), plate.layout)
    np.testing.assert_allclose(st.s, [0.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(st.e, e0, atol=1e-9)


def test_2d_bend_and_tilt():
    beam = beam_drone_2d()
    x = beam.fem.rest.copy()
    right = x[:, 0] > 0.6
    a, tilt = 0.3, -0.2
    c, s = np.cos(a), np.sin(a)
    pivot = np.array([0.6, T / 2])
    x[right] = (x[right] - pivot) @ np.array([[c, -s], [s, c]]).T + pivot
    c, s = np.cos(tilt), np.sin(tilt)
    x = x @ np.array([[c, -s], [s, c]]).T
    st = decompose(read_imus(0.0, x, np.zeros_like(x), beam.imus), beam.layout)
    np.testing.assert_allclose(st.e, [tilt], atol=1e-9)
    np.testing.assert_allclose(st.s, [0.0, a], atol=1e-9)


def test_euler_round_trip_and_rate_matrix():
    rng = np.random.default_rng(0)
    e = rng.uniform(-1.4, 1.4, (50, 3))
    np.testing.assert_allclose(euler_from_matrix(matrix_from_euler(e)), e, atol=1e-12)
    # omega from the time derivative of R(e(t)) matches E(e) e_dot
    e_dot = rng.standard_normal(3)
    h = 1e-6
    R0, R1 = matrix_from_euler(e[0] - h * e_dot), matrix_from_euler(e[0] + h * e_dot)
    W = (R1 - R0) / (2 * h) @ matrix_from_euler(e[0]).T
    omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
    np.testing.assert_allclose(euler_rates(e[0], omega), e_dot, atol=1e-6)
    np.testing.assert_allclose(W, skew(omega), atol=1e-6)


def test_average_of_symmetric_rotations_is_the_middle():
    e = np.array([0.2, 0.5, -0.1])
    d = np.array([0.0, 0.3, 0.0])
    avg = average_rotations(np.stack([matrix_from_euler(e + d), matrix_from_euler(e - d)]))
    np.testing.assert_allclose(avg, matrix_from_euler(e), atol=1e-9)


def test_sideways_twist_keeps_the_bend_angle_continuous(plate):
    """Twisting the right wing about its own radial axis tilts y_b sideways only: the bend
    angle stays zero (the paper's beta * arccos form would read +-angle and flip sign)."""
    x = plate.fem.rest.copy()
    sel = x[:, 0] > 0.6
    for angle in (-0.3, 0.3):
        R = matrix_from_euler(np.array([angle, 0.0, 0.0]))  # about x: the wing's radial axis
        xt = x.copy()
        xt[sel] = (x[sel] - [0, T / 2, 0]) @ R.T + [0, T / 2, 0]
        st = decompose(read_imus(0.0, xt, np.zeros_like(xt), plate.imus), plate.layout)
        assert st.s[1] == pytest.approx(0.0, abs=1e-9)
