"""The sensor placement rule of supplement D on layouts whose answer is known by hand."""
import numpy as np

from sdexp.sim.mesh.placement import rotor_tree, tree_imus


def test_flower_gets_one_imu_per_petal_near_the_tip():
    a = np.arange(8) * np.pi / 4
    rotors = np.r_[[[0.0, 0.0, 0.0]], np.c_[1.5 * np.cos(a), 0 * a, 1.5 * np.sin(a)]]
    imus = tree_imus(np.zeros(3), rotors, 8, root_radius=0.1)
    np.testing.assert_allclose(np.hypot(*imus.T), 0.8 * 1.5)
    np.testing.assert_allclose(np.mod(np.arctan2(imus[:, 1], imus[:, 0]), 2 * np.pi), a, atol=1e-12)


def test_collinear_rotors_form_a_chain_and_share_the_sensors():
    rotors = np.array([[-4.0, 0], [-2, 0], [0, 0], [2, 0], [4, 0]])
    edges = rotor_tree(np.zeros(2), rotors, 0.1)
    assert sorted((p[0], c[0]) for p, c, _ in edges) == [(-2, -4), (0, -2), (0, 2), (2, 4)]
    imus = tree_imus(np.zeros(2), rotors, 8, 0.1)
    np.testing.assert_allclose(np.sort(imus[:, 0]), [-3.6, -2.8, -1.6, -0.8, 0.8, 1.6, 2.8, 3.6])


def test_fewer_sensors_than_wings_spread_evenly():
    a = np.arange(4) * np.pi / 2
    rotors = np.c_[np.cos(a), np.sin(a)]
    imus = tree_imus(np.zeros(2), rotors, 2)
    np.testing.assert_allclose(imus, [[0.8, 0.0], [-0.8, 0.0]], atol=1e-12)
