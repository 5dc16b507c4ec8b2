"""The LQR core every controller shares: the infinite-horizon continuous-time gain from SciPy's
algebraic Riccati solver (supplement G), its sampled-data counterpart, and the diagonal cost of
the supplement's table.

Why a discrete option. The continuous gain assumes the command changes continuously; the loop
runs at 100 Hz with the command held for 10 ms. On the learned flower model the continuous
design places closed-loop poles near -200 /s (the bend angles s are cheap to move: B's s rows
reach 14 rad/s^2 per N), where the Euler-sampled loop x_{k+1} = (I + dt (A - B K)) x_k is
already unstable (|1 - 200 x 0.01| > 1). ``lqr_gain(..., dt=0.01)`` solves the discrete
Riccati equation of that sampled system, A_d = I + dt A, B_d = dt B (the same explicit step the
learned model takes), with the cost Q dt, R dt, so the gain is stable at the rate it runs at.
The paper's method is the continuous one (``control.riccati: continuous``, the default)."""
from __future__ import annotations

import numpy as np
import scipy.linalg


class LqrFailure(RuntimeError):
    """The Riccati equation has no stabilising solution for this (A, B, Q, R)."""


def _care_schur(A, B, Q, R) -> np.ndarray:
    """S from the stable invariant subspace of the Hamiltonian (Laub's Schur method): 3x faster
    than SciPy's extended-pencil QZ at 28 states (1.5 vs 4.7 ms on one core); R here is a well-
    conditioned diagonal, which is all the pencil form protects against."""
    n = len(A)
    H = np.block([[A, -B @ np.linalg.solve(R, B.T)], [-Q, -A.T]])
    _, Z, stable = scipy.linalg.schur(H, sort="lhp")
    if stable != n:
        raise np.linalg.LinAlgError("the Hamiltonian has eigenvalues on the imaginary axis")
    S = np.linalg.solve(Z[:n, :n].T, Z[n:, :n].T).T
    return 0.5 * (S + S.T)


def _care_gain(A, B, Q, R) -> np.ndarray:
    try:
        K = _checked_gain(A, B, Q, R, _care_schur(A, B, Q, R))
        if K is not None:
            return K
    except np.linalg.LinAlgError:
        pass
    S = scipy.linalg.solve_continuous_are(A, B, Q, R)   # the careful solver, when the fast one fails
    K = _checked_gain(A, B, Q, R, S)
    if K is None:
        raise np.linalg.LinAlgError("the Riccati solution does not solve the equation (ill-posed)")
    return K


def _checked_gain(A, B, Q, R, S) -> np.ndarray | None:
    K = np.linalg.solve(R, B.T @ S)
    # With a marginal mode that roundoff alone makes "controllable" (rotor normals off +y by
    # 1e-16), SciPy can return instead of failing: |S| ~ 1e15, gains up to 1e8, and a Riccati
    # residual ~ 1e9 |Q|. Such an S solves nothing; treat it as the failure it is.
    res = S @ A + A.T @ S - S @ B @ K + Q
    if not np.all(np.isfinite(K)) or np.abs(res).max() > 1e-4 * max(np.abs(Q).max(), 1e-300):
        return None
    # a solution of the equation is the LQR one only if it stabilises (marginal modes can give
    # non-stabilising solutions with a small residual)
    if np.linalg.eigvals(A - B @ K).real.max() >= 0:
        return None
    return K


def _dare_gain(A, B, Q, R, dt: float) -> np.ndarray:
    Ad, Bd = np.eye(len(A)) + dt * A, dt * B
    P = scipy.linalg.solve_discrete_are(Ad, Bd, Q * dt, R * dt)
    K = np.linalg.solve(R * dt + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
    res = Ad.T @ P @ Ad - P - Ad.T @ P @ Bd @ K + Q * dt
    if not np.all(np.isfinite(K)) or np.abs(res).max() > 1e-4 * max(np.abs(Q * dt).max(), 1e-300):
        raise np.linalg.LinAlgError("the discrete Riccati solution does not solve the equation (ill-posed)")
    return K


def controllable_basis(A: np.ndarray, B: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis (columns) of the controllable subspace span[B, AB, ..., A^(n-1) B], by
    the orthogonal staircase: each block A v of the newest directions v is orthogonalised against
    the basis so far and kept where it exceeds rtol |A| (rtol |B| for B itself). The explicit
    matrix [B, AB, ...] would let the powers of A swamp B (a generic 28-state model read as rank
    13)."""
    n = len(A)
    V = np.zeros((n, 0))
    W, scale = B, np.linalg.norm(B, 2)
    while V.shape[1] < n:
        for _ in range(2):                      # twice is enough (Kahan)
            W = W - V @ (V.T @ W)
        U, sv, _ = np.linalg.svd(W, full_matrices=False)
        new = U[:, sv > rtol * scale][:, : n - V.shape[1]]
        if new.shape[1] == 0 or scale == 0:
            break
        V = np.hstack([V, new])
        W, scale = A @ new, np.linalg.norm(A, 2)
    return V


def lqr_gain(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, dt: float | None = None,
             states: np.ndarray | None = None) -> np.ndarray:
    """K = R^-1 B^T S with 0 = S A + A^T S - S B R^-1 B^T S + Q; with ``dt`` the gain of the
    sampled system (module docstring). ``states``: the indices of x the controller regulates; the
    gain is designed on their rows and columns of A, B and Q alone and is zero on the others
    (None: all of them).

    A system with uncontrollable marginal modes (a rigid multicopter without rotor reaction
    torque cannot yaw) has no stabilising Riccati solution; then the gain is designed on the
    controllable subspace T (A_c = T^T A T, B_c = T^T B, Q_c = T^T Q T) and K = K_c T^T, which
    leaves the uncontrollable modes alone -- nothing could move them. An uncontrollable mode
    that grows (the system is not stabilisable) raises LqrFailure."""
    if states is not None and len(states) < len(A):
        K = np.zeros((B.shape[1], len(A)))
        K[:, states] = lqr_gain(A[np.ix_(states, states)], B[states], Q[np.ix_(states, states)], R, dt)
        return K
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        raise LqrFailure("A or B is not finite")
    gain = _care_gain if dt is None else (lambda *m: _dare_gain(*m, dt))
    try:
        return gain(A, B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as first:
        T = controllable_basis(A, B)
        if T.shape[1] in (0, len(A)):
            raise LqrFailure(str(first)) from first
        # the modes no input reaches: A on the orthogonal complement of the (A-invariant) span T
        N = scipy.linalg.null_space(T.T)
        growth = np.linalg.eigvals(N.T @ A @ N).real.max()
        if growth > 1e-6 * max(1.0, np.abs(A).max()):
            raise LqrFailure(f"{first}; an uncontrollable mode grows at rate {growth:.3g}") from first
        try:
            return gain(T.T @ A @ T, T.T @ B, T.T @ Q @ T, R) @ T.T
        except (np.linalg.LinAlgError, ValueError) as err:
            raise LqrFailure(f"{first}; on the controllable subspace: {err}") from err


def state_length(sizes: dict[str, int]) -> int:
    """The length of x = (s, s_dot, e, e_dot, p, p_dot)."""
    return 2 * (int(sizes["n_s"]) + int(sizes["n_e"]) + int(sizes["dim"]))


def regulated_states(sizes: dict[str, int], bend_spread, angle_noise: float, snr: float) -> np.ndarray:
    """Indices of x = (s, s_dot, e, e_dot, p, p_dot) the LQR regulates: every attitude and position
    channel, and the bends (with their rates) whose spread in the training data, ``bend_spread``
    (rad, one per bend), is at least ``snr`` times the IMU angle noise ``angle_noise`` (rad). Below
    that a bend channel is sensor noise and its learned dynamics a fit to noise: on the stiff drones
    (hover thrust bends them 0.04-0.17 deg under 0.573 deg of noise; spread 1.4-1.6x the noise) the
    fit has unstable or barely reachable bend modes and the LQR answers them with gains of
    200-500 N/rad, saturated alternating thrust. snr = 0 or no spread known: every channel."""
    n_s = int(sizes["n_s"])
    keep = np.ones(state_length(sizes), bool)
    if snr > 0 and bend_spread is not None and n_s:
        noisy = np.asarray(bend_spread, dtype=float) < snr * angle_noise
        keep[:n_s] &= ~noisy
        keep[n_s:2 * n_s] &= ~noisy
    return np.flatnonzero(keep)


def state_weights(sizes: dict[str, int], q_s: float, q_e: float, q_p: float, velocity_scale: float,
                  q_p_axes=None, q_e_axes=None) -> np.ndarray:
    """Diagonal of Q over (s, s_dot, e, e_dot, p, p_dot): the supplement's gains for s, e and p,
    their rates weighted ``velocity_scale`` times as much; ``q_p_axes`` and ``q_e_axes`` (one
    factor per axis / Euler angle) weigh the components apart, e.g. Z held tighter than the
    direction of travel, or yaw left loose where the rotors can hardly turn the body about its
    up axis (counter-rotating pairs, no reaction torque)."""
    def per(n: int, axes) -> np.ndarray:
        return np.ones(n) if axes is None else np.asarray(axes, dtype=float)
    parts = []
    for gain in (np.full(sizes["n_s"], float(q_s)), q_e * per(sizes["n_e"], q_e_axes), q_p * per(sizes["dim"], q_p_axes)):
        parts += [gain, gain * velocity_scale]
    return np.concatenate(parts)


def alike_groups(bend_targets) -> list[np.ndarray]:
    """The bend channels a task moves together: per keyframe of ``bend_targets`` ((k, n_s), rad),
    the channels sharing one non-zero target, each group (of two or more) once."""
    groups: dict[tuple, np.ndarray] = {}
    for target in np.atleast_2d(np.asarray(bend_targets, dtype=float)):
        for value in np.unique(target[target != 0]):
            members = np.flatnonzero(target == value)
            if len(members) > 1:
                groups[tuple(members)] = members
    return list(groups.values())


def alike_weights(sizes: dict[str, int], groups, q: float, velocity_scale: float) -> np.ndarray:
    """Q's term q * sum over each group's pairs of (s_a - s_b)^2 (and velocity_scale x that on the
    rates), a matrix over x = (s, s_dot, e, e_dot, p, p_dot): the cost of bends asked to move
    together parting. Not in the paper: the star's two folding wings fold 15-50 deg apart under
    the diagonal Q, and the less-folded wing meets a block (docs/results.md, "Obstacle")."""
    n_s, n = int(sizes["n_s"]), state_length(sizes)
    W = np.zeros((n, n))
    for members in groups:
        L = q * _laplacian(len(members))
        W[np.ix_(members, members)] += L
        W[np.ix_(n_s + members, n_s + members)] += velocity_scale * L
    return W


def _laplacian(k: int) -> np.ndarray:
    """The complete graph's Laplacian on k members: v @ L @ v = sum over pairs of (v_a - v_b)^2."""
    return k * np.eye(k) - np.ones((k, k))


def alike_rotors(B_bend_rates: np.ndarray, groups) -> list[np.ndarray]:
    """Per group of bends moved together, the rotors that drive them: for each bend the rotor whose
    thrust accelerates it most (the largest |d s_ddot / d u| in the learned model's B), a group
    kept where two or more distinct rotors remain. Read from the model, not from the mesh, so it
    holds for any drone the learning side sees."""
    out = []
    for members in groups:
        rotors = np.unique(np.argmax(np.abs(B_bend_rates[members]), axis=1))
        if len(rotors) > 1:
            out.append(rotors)
    return out


def alike_thrust_weights(m: int, rotor_groups, r: float) -> np.ndarray:
    """R's term r * sum over each group's pairs of (u_a - u_b)^2, (m, m): thrust differences among
    the rotors of bends asked to move together cost extra, their common thrust does not. Not in the
    paper: on the folded star one thrust difference drives roll, the Z push and the wings' parting
    at once (docs/results.md, "Obstacle"); this prices that input instead of its outcome (alike_weights)."""
    W = np.zeros((m, m))
    for rotors in rotor_groups:
        W[np.ix_(rotors, rotors)] += r * _laplacian(len(rotors))
    return W
