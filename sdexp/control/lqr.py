"""The LQR core every controller shares: the infinite-horizon continuous-time gain from SciPy's
algebraic Riccati solver (supplement G), and the diagonal cost of the supplement's table."""
from __future__ import annotations

import numpy as np
import scipy.linalg


class LqrFailure(RuntimeError):
    """The Riccati equation has no stabilising solution for this (A, B, Q, R)."""


def _care_gain(A, B, Q, R) -> np.ndarray:
    S = scipy.linalg.solve_continuous_are(A, B, Q, R)
    return np.linalg.solve(R, B.T @ S)


def controllable_basis(A: np.ndarray, B: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis (columns) of the controllable subspace span[B, AB, ..., A^(n-1) B]."""
    n = len(A)
    blocks, M = [B], B
    for _ in range(n - 1):
        M = A @ M
        blocks.append(M)
    C = np.hstack(blocks)
    U, sv, _ = np.linalg.svd(C / max(np.abs(C).max(), 1e-300), full_matrices=False)
    return U[:, sv > rtol * sv[0]] if len(sv) and sv[0] > 0 else np.zeros((n, 0))


def lqr_gain(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """K = R^-1 B^T S with 0 = S A + A^T S - S B R^-1 B^T S + Q.

    A system with uncontrollable marginal modes (a rigid multicopter without rotor reaction
    torque cannot yaw) has no stabilising Riccati solution; then the gain is designed on the
    controllable subspace T (A_c = T^T A T, B_c = T^T B, Q_c = T^T Q T) and K = K_c T^T, which
    leaves the uncontrollable modes alone -- nothing could move them."""
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        raise LqrFailure("A or B is not finite")
    try:
        return _care_gain(A, B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as first:
        T = controllable_basis(A, B)
        if T.shape[1] in (0, len(A)):
            raise LqrFailure(str(first)) from first
        try:
            return _care_gain(T.T @ A @ T, T.T @ B, T.T @ Q @ T, R) @ T.T
        except (np.linalg.LinAlgError, ValueError) as err:
            raise LqrFailure(f"{first}; on the controllable subspace: {err}") from err


def state_weights(sizes: dict[str, int], q_s: float, q_e: float, q_p: float, velocity_scale: float) -> np.ndarray:
    """Diagonal of Q over (s, s_dot, e, e_dot, p, p_dot): the supplement's gains for s, e and p,
    their rates weighted ``velocity_scale`` times as much."""
    parts = []
    for gain, n in ((q_s, sizes["n_s"]), (q_e, sizes["n_e"]), (q_p, sizes["dim"])):
        parts += [np.full(n, gain), np.full(n, gain * velocity_scale)]
    return np.concatenate(parts)
