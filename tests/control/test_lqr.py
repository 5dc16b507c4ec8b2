"""lqr_gain against closed forms and against the optimality conditions of the Riccati equation;
the controllable-subspace fallback; the diagonal cost of supplement G."""
import numpy as np
import pytest
import scipy.linalg

from sdexp.control.lqr import (LqrFailure, alike_groups, alike_rotors, alike_thrust_weights, alike_weights, controllable_basis, lqr_gain,
                               regulated_states, state_weights)

DOUBLE_INTEGRATOR = (np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]))


def analytic_double_integrator_gain(q1, q2, r):
    """x'' = u, cost q1 x^2 + q2 x'^2 + r u^2: K = [sqrt(q1/r), sqrt(q2/r + 2 sqrt(q1/r))]."""
    k1 = np.sqrt(q1 / r)
    return np.array([[k1, np.sqrt(q2 / r + 2 * k1)]])


def assert_hurwitz(M, margin=1e-9):
    assert np.linalg.eigvals(M).real.max() < -margin


def riccati_from_gain(A, B, Q, R, K):
    """The cost-to-go S of the policy u = -K x (Lyapunov equation of the closed loop). K is the
    LQR gain iff the loop is stable and K = R^-1 B^T S; S then solves the Riccati equation."""
    Acl = A - B @ K
    return scipy.linalg.solve_continuous_lyapunov(Acl.T, -(Q + K.T @ R @ K))


@pytest.mark.parametrize("q1, q2, r", [(1.0, 1.0, 1.0), (100.0, 100.0, 2.0), (200.0, 0.0, 2.0), (4.0, 9.0, 0.25)])
def test_double_integrator_gain_is_the_closed_form(q1, q2, r):
    A, B = DOUBLE_INTEGRATOR
    K = lqr_gain(A, B, np.diag([q1, q2]), np.array([[r]]))
    expect = analytic_double_integrator_gain(q1, q2, r)
    np.testing.assert_allclose(K, expect, rtol=1e-8)
    assert_hurwitz(A - B @ K)
    # S = r [[k1 k2, k1], [k1, k2]] solves 0 = SA + A^T S - S B R^-1 B^T S + Q
    k1, k2 = expect[0]
    S = r * np.array([[k1 * k2, k1], [k1, k2]])
    res = S @ A + A.T @ S - S @ B @ B.T @ S / r + np.diag([q1, q2])
    assert np.abs(res).max() < 1e-9 * max(q1, q2, 1.0)
    np.testing.assert_allclose(K, B.T @ S / r, rtol=1e-8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_system_gain_satisfies_the_riccati_optimality_conditions(seed):
    rng = np.random.default_rng(seed)
    n, m = 6, 2
    A = rng.normal(size=(n, n))            # open loop typically unstable
    B = rng.normal(size=(n, m))
    L = rng.normal(size=(n, n))
    Q = L @ L.T + 0.1 * np.eye(n)
    R = np.diag(rng.uniform(0.5, 3.0, m))
    K = lqr_gain(A, B, Q, R)
    assert K.shape == (m, n)
    assert_hurwitz(A - B @ K)
    S = riccati_from_gain(A, B, Q, R, K)
    np.testing.assert_allclose(K, np.linalg.solve(R, B.T @ S), atol=1e-8 * np.abs(K).max())
    res = S @ A + A.T @ S - S @ B @ np.linalg.solve(R, B.T @ S) + Q
    assert np.abs(res).max() < 1e-8 * np.abs(S).max()
    # optimal: any perturbed stabilising gain costs more from every initial state
    for _ in range(5):
        K2 = K + 0.05 * rng.normal(size=K.shape)
        if np.linalg.eigvals(A - B @ K2).real.max() < 0:
            S2 = riccati_from_gain(A, B, Q, R, K2)
            assert np.linalg.eigvalsh(S2 - S).min() > -1e-9 * np.abs(S).max()


def _uncontrollable_pair():
    """Two decoupled double integrators, only the first actuated: the second is a marginal
    (double zero eigenvalue) mode nothing can move, like a rigid multicopter's yaw."""
    A = np.zeros((4, 4))
    A[0, 1] = A[2, 3] = 1.0
    B = np.array([[0.0], [1.0], [0.0], [0.0]])
    return A, B


def test_scipy_fails_on_an_uncontrollable_marginal_mode():
    A, B = _uncontrollable_pair()
    with pytest.raises((np.linalg.LinAlgError, ValueError)):
        scipy.linalg.solve_continuous_are(A, B, np.eye(4), np.eye(1))


@pytest.mark.parametrize("q, r", [((1.0, 1.0, 5.0, 5.0), 1.0), ((100.0, 50.0, 100.0, 100.0), 2.0)])
def test_fallback_designs_on_the_controllable_subspace(q, r):
    A, B = _uncontrollable_pair()
    K = lqr_gain(A, B, np.diag(q), np.array([[r]]))
    assert K.shape == (1, 4)
    # no feedback from the states the input cannot move ...
    assert np.abs(K[:, 2:]).max() < 1e-12
    # ... and the optimal gain of the actuated double integrator on the rest
    np.testing.assert_allclose(K[:, :2], analytic_double_integrator_gain(q[0], q[1], r), rtol=1e-8)
    assert_hurwitz((A - B @ K)[:2, :2])


def test_fallback_with_a_rotated_state_basis():
    """The same system in mixed coordinates z = P x: the gain is the rotated one, K P^-1."""
    A, B = _uncontrollable_pair()
    P = np.linalg.qr(np.random.default_rng(3).normal(size=(4, 4)))[0]
    Az, Bz = P @ A @ P.T, P @ B
    Q = np.diag([2.0, 3.0, 1.0, 1.0])
    Kz = lqr_gain(Az, Bz, P @ Q @ P.T, np.eye(1))
    K = Kz @ P
    assert np.abs(K[:, 2:]).max() < 1e-9
    np.testing.assert_allclose(K[:, :2], analytic_double_integrator_gain(2.0, 3.0, 1.0), rtol=1e-7)


def test_unstable_uncontrollable_mode_is_a_failure():
    """Not stabilisable (an uncontrollable mode grows as e^t): no gain can be right."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    B = np.array([[0.0], [1.0], [0.0]])
    with pytest.raises(LqrFailure):
        lqr_gain(A, B, np.eye(3), np.eye(1))
    # the same mode decaying is harmless: SciPy solves it directly
    A[2, 2] = -1.0
    K = lqr_gain(A, B, np.eye(3), np.eye(1))
    assert_hurwitz(A - B @ K)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_model_raises_lqr_failure(bad):
    A, B = DOUBLE_INTEGRATOR
    A = A.copy()
    A[1, 0] = bad
    with pytest.raises(LqrFailure):
        lqr_gain(A, B, np.eye(2), np.eye(1))
    B = B.copy()
    B[1, 0] = bad
    with pytest.raises(LqrFailure):
        lqr_gain(DOUBLE_INTEGRATOR[0], B, np.eye(2), np.eye(1))


def test_no_input_at_all_is_a_failure():
    A, _ = DOUBLE_INTEGRATOR
    with pytest.raises(LqrFailure):
        lqr_gain(A, np.zeros((2, 1)), np.eye(2), np.eye(1))


@pytest.mark.parametrize("eps", [1e-16, 1e-14, 1e-12])
def test_roundoff_controllability_does_not_blow_up_the_gain(eps):
    """Yaw of a symmetric quad without reaction torque is uncontrollable; rotor normals off +y
    by roundoff make it numerically 'controllable' with authority ~eps. SciPy's CARE may then
    return a meaningless S (|S| ~ 1e15+, gains up to 1e8) instead of failing. The gain must be
    the exact-geometry one: yaw left alone, everything else as with exact normals."""
    from sdexp.control.rigid import RigidGeometry, linearize_rigid

    pos = np.array([[0.5, 0.05, 0.0], [-0.5, 0.05, 0.0], [0.0, 0.05, 0.5], [0.0, 0.05, -0.5]])
    J = np.diag([0.1, 0.2, 0.1])
    Q, R = 100.0 * np.eye(12), 2.0 * np.eye(4)

    def gain(dirs):
        g = RigidGeometry(1.0, J, pos, dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
        A, B = linearize_rigid(g, 9.81, np.zeros(12), g.hover_thrust(9.81))
        return lqr_gain(A, B, Q, R)

    up = np.tile([0.0, 1.0, 0.0], (4, 1))
    K0 = gain(up)
    for seed in range(4):
        K = gain(up + eps * np.random.default_rng(seed).normal(size=(4, 3)))
        np.testing.assert_allclose(K, K0, atol=1e-5 * np.abs(K0).max())


def test_controllable_basis_is_scale_robust():
    """A 28-state, 9-input model like the flower's learned one (velocity rows ~ 1/alpha): the
    powers of A in [B, AB, ..., A^27 B] span 1e50 and must not hide directions reached early."""
    rng = np.random.default_rng(0)
    n, m = 28, 9
    A = np.zeros((n, n))
    A[:14, 14:] = np.eye(14)
    A[14:] = 100.0 * rng.normal(size=(14, n))
    B = np.zeros((n, m))
    B[14:] = rng.normal(size=(14, m))
    assert controllable_basis(A, B).shape == (n, n)
    # a known split hidden in a rotated basis: 6 controllable states, 4 that nothing reaches
    Ac = 50.0 * rng.normal(size=(6, 6))
    Au = rng.normal(size=(4, 4))
    Afull = scipy.linalg.block_diag(Ac, Au)
    Afull[:6, 6:] = rng.normal(size=(6, 4))           # the hidden states may drive the others
    Bfull = np.r_[rng.normal(size=(6, 1)), np.zeros((4, 1))]
    P = np.linalg.qr(rng.normal(size=(10, 10)))[0]
    T = controllable_basis(P @ Afull @ P.T, P @ Bfull)
    assert T.shape == (10, 6)
    np.testing.assert_allclose(T @ T.T, P[:, :6] @ P[:, :6].T, atol=1e-8)


def test_controllable_basis_spans_the_krylov_space():
    A, B = _uncontrollable_pair()
    T = controllable_basis(A, B)
    assert T.shape == (4, 2)
    np.testing.assert_allclose(T.T @ T, np.eye(2), atol=1e-12)
    # span{e1, e2}: the projector onto it
    np.testing.assert_allclose(T @ T.T, np.diag([1.0, 1.0, 0.0, 0.0]), atol=1e-12)
    # a chain of integrators driven at the end is fully controllable
    n = 5
    A = np.eye(n, k=1)
    B = np.eye(n)[:, [-1]]
    assert controllable_basis(A, B).shape == (n, n)
    assert controllable_basis(A, np.zeros((n, 1))).shape == (n, 0)


def test_state_weights_follow_the_state_layout():
    q = state_weights({"n_s": 2, "n_e": 1, "dim": 2}, q_s=100.0, q_e=50.0, q_p=200.0, velocity_scale=0.5)
    # (s, s_dot, e, e_dot, p, p_dot)
    np.testing.assert_array_equal(q, [100, 100, 50, 50, 50, 25, 200, 200, 100, 100])
    q3 = state_weights({"n_s": 0, "n_e": 3, "dim": 3}, 1.0, 2.0, 3.0, 1.0)
    np.testing.assert_array_equal(q3, [2, 2, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3])
    # Z held ten times tighter than X and Y, its velocity too
    qz = state_weights({"n_s": 1, "n_e": 3, "dim": 3}, 1.0, 2.0, 3.0, 0.5, q_p_axes=[1, 1, 10])
    np.testing.assert_array_equal(qz[-6:], [3, 3, 30, 1.5, 1.5, 15])
    # yaw (e_y, about the up axis) left loose
    qy = state_weights({"n_s": 1, "n_e": 3, "dim": 3}, 1.0, 2.0, 3.0, 0.5, q_e_axes=[1, 0.01, 1])
    np.testing.assert_allclose(qy[2:8], [2, 0.02, 2, 1, 0.01, 1])


def test_sampled_gain_approaches_the_continuous_one_and_stays_stable_where_it_does_not():
    """lqr_gain(dt=...) designs for x_{k+1} = (I + dt A) x_k + dt B u_k: as dt -> 0 it tends to
    the continuous gain; at a coarse step the continuous gain's sampled loop is unstable while
    the sampled design's is not."""
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    Q, R = np.diag([1e6, 1.0]), np.eye(1)       # continuous poles at -22 +- 22j
    Kc = lqr_gain(A, B, Q, R)
    assert np.allclose(lqr_gain(A, B, Q, R, dt=1e-6), Kc, rtol=1e-2)
    dt = 0.05
    Kd = lqr_gain(A, B, Q, R, dt=dt)
    radius = lambda K: np.abs(np.linalg.eigvals(np.eye(2) + dt * (A - B @ K))).max()
    assert radius(Kc) > 1.0 > radius(Kd)


def test_bends_whose_spread_is_sensor_noise_are_not_regulated():
    sizes = {"n_s": 3, "n_e": 1, "dim": 2}      # x: s(3), s_dot(3), e, e_dot, p(2), p_dot(2)
    noise = np.radians(0.573)
    # bend 1 spreads 1.5x the noise (a stiff body's), bends 0 and 2 well above 3x
    spread = np.array([0.2, 1.5 * noise, 4 * noise])
    np.testing.assert_array_equal(regulated_states(sizes, spread, noise, 3.0), [0, 2, 3, 5, 6, 7, 8, 9, 10, 11])
    everything = np.arange(12)
    np.testing.assert_array_equal(regulated_states(sizes, spread, noise, 0.0), everything)   # the paper
    np.testing.assert_array_equal(regulated_states(sizes, None, noise, 3.0), everything)     # spread unknown
    np.testing.assert_array_equal(regulated_states(sizes, spread, 0.0, 3.0), everything)     # noise-free sensors
    assert len(regulated_states({"n_s": 0, "n_e": 3, "dim": 3}, None, noise, 3.0)) == 12


def test_a_gain_on_some_states_is_their_subsystems_gain_and_zero_elsewhere():
    """A double integrator (states 1, 2) beside a spurious unstable mode (state 0) that the input
    barely reaches and that drives nothing: on every state the LQR must spend a large gain on the
    spurious mode; on states 1, 2 it is the double integrator's closed form, exactly zero on 0."""
    A = np.array([[5.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    B = np.array([[1e-3], [0.0], [1.0]])
    Q, R = np.diag([100.0, 100.0, 100.0]), np.array([[2.0]])
    full = lqr_gain(A, B, Q, R)
    assert abs(full[0, 0]) > 1e3 * abs(full[0, 1])
    K = lqr_gain(A, B, Q, R, states=np.array([1, 2]))
    assert K[0, 0] == 0.0
    np.testing.assert_allclose(K[:, 1:], analytic_double_integrator_gain(100.0, 100.0, 2.0), rtol=1e-9)
    np.testing.assert_array_equal(lqr_gain(A, B, Q, R, states=np.arange(3)), full)


def test_alike_groups_are_the_bends_one_keyframe_moves_to_one_value():
    a, b = 0.3, 0.5
    groups = alike_groups([[0, 0, 0, 0, 0], [a, 0, a, b, 0], [a, 0, a, b, b]])
    assert sorted(g.tolist() for g in groups) == [[0, 2], [3, 4]]   # [3] alone is no group; [0, 2] once
    assert alike_groups([[0.0, 0.0, 0.0]]) == [] and alike_groups(np.zeros((0, 3))) == []


def test_alike_weights_cost_the_parting_of_bends_and_nothing_else():
    sizes, q, vs = {"n_s": 4, "n_e": 3, "dim": 3}, 7.0, 0.5
    W = alike_weights(sizes, [np.array([0, 2, 3])], q, vs)
    x = np.random.default_rng(0).normal(size=len(W))
    s, sd = x[:4], x[4:8]
    pairs = [(0, 2), (0, 3), (2, 3)]
    expect = q * sum((s[i] - s[j]) ** 2 for i, j in pairs) + vs * q * sum((sd[i] - sd[j]) ** 2 for i, j in pairs)
    assert x @ W @ x == pytest.approx(expect, rel=1e-12)
    assert np.all(W[8:] == 0) and np.all(W[:, 8:] == 0) and np.all(W[1] == 0)   # e, p, and bend 1 untouched
    np.testing.assert_array_equal(W, W.T)


@pytest.mark.parametrize("q, q_alike, r", [(100.0, 30.0, 10.0), (1.0, 4.0, 0.5)])
def test_the_alike_weight_stiffens_the_differential_bend_mode_alone(q, q_alike, r):
    # two bends, each a double integrator with its own input: in the basis of common and
    # differential modes, (s1 + s2) / sqrt 2 keeps the gain of weight q and (s1 - s2) / sqrt 2 gets
    # that of q + 2 q_alike (q_alike (s1 - s2)^2 = 2 q_alike d^2), rates alike (velocity_scale 1)
    A = np.block([[np.zeros((2, 2)), np.eye(2)], [np.zeros((2, 4))]])
    B = np.vstack([np.zeros((2, 2)), np.eye(2)])
    Q = q * np.eye(4) + alike_weights({"n_s": 2, "n_e": 0, "dim": 0}, [np.array([0, 1])], q_alike, 1.0)
    K = lqr_gain(A, B, Q, r * np.eye(2))
    c, d = np.array([1.0, 1.0]) / np.sqrt(2), np.array([1.0, -1.0]) / np.sqrt(2)
    for mode, weight in ((c, q), (d, q + 2 * q_alike)):
        gain = mode @ K @ np.kron(np.eye(2), mode[:, None])     # (angle, rate) gain of that mode
        np.testing.assert_allclose(gain, analytic_double_integrator_gain(weight, weight, r)[0], rtol=1e-8)


def test_alike_rotors_are_each_bends_strongest_rotor_and_need_two():
    B = np.array([[0.1, 2.0, 0.0, 0.3],     # bend 0: rotor 1
                  [0.0, 0.1, -0.2, 0.0],    # bend 1: rotor 2 (the magnitude counts)
                  [0.5, 0.0, 0.0, 0.1],     # bend 2: rotor 0
                  [0.0, 0.0, 0.0, 1.0]])    # bend 3: rotor 3
    groups = alike_rotors(B, [np.array([0, 2]), np.array([1, 3]), np.array([0, 0])])
    assert [g.tolist() for g in groups] == [[0, 1], [2, 3]]   # bends 0 and 0 share one rotor: no group


def test_alike_thrust_weights_cost_thrust_differences_and_not_the_common_thrust():
    W = alike_thrust_weights(5, [np.array([1, 3, 4])], 2.5)
    u = np.random.default_rng(1).normal(size=5)
    pairs = [(1, 3), (1, 4), (3, 4)]
    assert u @ W @ u == pytest.approx(2.5 * sum((u[i] - u[j]) ** 2 for i, j in pairs), rel=1e-12)
    assert np.allclose(W @ np.array([0, 1, 0, 1, 1.0]), 0) and np.all(W[0] == 0) and np.all(W[2] == 0)


@pytest.mark.parametrize("q, r, r_alike", [(100.0, 10.0, 3.0), (1.0, 0.5, 0.2)])
def test_the_alike_thrust_weight_softens_the_differential_input_mode_alone(q, r, r_alike):
    # two bends, each a double integrator with its own input: the common mode keeps the gain of R = r,
    # the differential one gets that of r + 2 r_alike r (r_alike r (u1 - u2)^2 = 2 r_alike r d^2)
    A = np.block([[np.zeros((2, 2)), np.eye(2)], [np.zeros((2, 4))]])
    B = np.vstack([np.zeros((2, 2)), np.eye(2)])
    R = r * np.eye(2) + alike_thrust_weights(2, [np.array([0, 1])], r_alike * r)
    K = lqr_gain(A, B, q * np.eye(4), R)
    c, d = np.array([1.0, 1.0]) / np.sqrt(2), np.array([1.0, -1.0]) / np.sqrt(2)
    for mode, weight in ((c, r), (d, r + 2 * r_alike * r)):
        gain = mode @ K @ np.kron(np.eye(2), mode[:, None])
        np.testing.assert_allclose(gain, analytic_double_integrator_gain(q, q, weight)[0], rtol=1e-8)
