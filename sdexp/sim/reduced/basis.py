"""The floating frame and the deformation basis.

Frame: the centre of mass and a rotation; the deformation u lives in the body frame,
x_i = c + R (X_i + u_i) with X the rest shape about its centre of mass. The basis Phi is
mass-orthonormal (Phi^T M Phi = 1) and mass-orthogonal to the rigid motions at rest (sum m Phi = 0,
sum m X x Phi = 0: the linearised Tisserand frame), so c stays the centre of mass exactly and the
frame carries the rigid rotation to first order.

Basis = the first free-free linear modes (exact, so the low frequencies are the full model's) plus
a mass-weighted PCA of full-FEM snapshots with the rigid motion removed (a best-fit rotation), in
what the linear modes leave: the snapshots carry the large, rotated deformations of flight that
linear modes alone miss (DESIGN.md: free-free modes alone 25% off at 40, PCA 2.4% at 80).
"""
from __future__ import annotations

import numpy as np

from sdexp.sim.physics.modes import rigid_modes


def centred_rest(rest: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(X, com): the rest shape about its centre of mass and that centre."""
    com = mass @ rest / mass.sum()
    return rest - com, com


def best_fit_frame(x: np.ndarray, X: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(c, R): the centre of mass of x (nv, d) and the rotation minimising sum m |x - c - R X|^2
    (mass-weighted Kabsch); X is the rest shape about its centre of mass."""
    c = mass @ x / mass.sum()
    A = (x - c).T @ (mass[:, None] * X)
    U, _, Vt = np.linalg.svd(A)
    D = np.eye(len(c))
    D[-1, -1] = np.sign(np.linalg.det(U @ Vt))
    return c, U @ D @ Vt


def deformations(xs: np.ndarray, X: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Each snapshot's deformation in its best-fit frame, (S, nv, d)."""
    out = np.empty_like(xs)
    for s, x in enumerate(xs):
        c, R = best_fit_frame(x, X, mass)
        out[s] = (x - c) @ R - X
    return out


def rigid_basis(X: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Mass-orthonormal translations and infinitesimal rotations, (nv d, 6 | 3) (modes.rigid_modes'
    span: about which point the rotations turn does not change it)."""
    return mass_orthonormal(rigid_modes(X), np.repeat(mass, X.shape[1]))


def mass_orthonormal(V: np.ndarray, m: np.ndarray, against: np.ndarray | None = None,
                     drop: float = 1e-10) -> np.ndarray:
    """The columns of V (n, k) made orthonormal in the inner product a^T diag(m) b (twice
    Gram-Schmidt through QR), after removing their part along ``against`` (mass-orthonormal
    columns); columns left with less than ``drop`` of their norm are dropped."""
    V = np.array(V, dtype=float)
    s = np.sqrt(m)[:, None]
    for _ in range(2):
        if against is not None and against.shape[1]:
            V -= against @ (against.T @ (m[:, None] * V))
        Q, Rr = np.linalg.qr(s * V)
        keep = np.abs(np.diag(Rr)) > drop * max(1.0, np.abs(np.diag(Rr)).max())
        V = Q[:, keep] / s
    return V


def deformation_basis(X: np.ndarray, mass: np.ndarray, modes: np.ndarray, snapshots: np.ndarray,
                      size: int) -> tuple[np.ndarray, np.ndarray]:
    """(Phi (nv d, size), captured): the ``modes`` (nv d, L: linear modes, static responses) and the
    leading mass-weighted principal components of the snapshot deformations (S, nv, d) in what
    the rigid motions and the modes leave; ``captured``: the share of the snapshots' squared
    mass-norm the whole basis holds."""
    m = np.repeat(mass, X.shape[1])
    rigid = rigid_basis(X, mass)
    lin = mass_orthonormal(modes, m, against=rigid)[:, :size]
    U = snapshots.reshape(len(snapshots), -1).T                      # (nv d, S)
    U = U - rigid @ (rigid.T @ (m[:, None] * U))
    total = float(np.sum(m[:, None] * U * U))
    rest = U - lin @ (lin.T @ (m[:, None] * U))
    k = size - lin.shape[1]
    if k > 0:
        s = np.sqrt(m)[:, None]
        W, sv, _ = np.linalg.svd(s * rest, full_matrices=False)
        pca = mass_orthonormal(W[:, :k] / s, m, against=np.c_[rigid, lin])
        Phi = np.c_[lin, pca]
    else:
        Phi = lin
    held = Phi.T @ (m[:, None] * U)
    return Phi, float(np.sum(held * held) / max(total, 1e-300))


def static_responses(K, X: np.ndarray, mass: np.ndarray, loads: np.ndarray) -> np.ndarray:
    """The free body's quasi-static deformation under each load (nv d, k), with inertia relief:
    the load less the rigid acceleration it gives, solved on K + eps M (K is singular on the
    rigid motions, which a balanced load does not excite: eps shifts the elastic response by
    about eps / omega_1^2, 1e-8 of it)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu
    m = np.repeat(mass, X.shape[1])
    rigid = rigid_basis(X, mass)
    balanced = loads - (m[:, None] * rigid) @ (rigid.T @ loads)
    eps = 1e-8 * float(K.diagonal().mean() / m.mean())
    out = splu(sp.csc_matrix(K + eps * sp.diags(m))).solve(np.asarray(balanced, float))
    return out - rigid @ (rigid.T @ (m[:, None] * out))


def modal_derivatives(K, X: np.ndarray, mass: np.ndarray, modes: np.ndarray, force) -> np.ndarray:
    """The static modal derivatives of ``modes`` (nv d, L) (Barbic and James 2005): for each pair
    i <= j the quasi-static response to the second derivative of the internal force along them,
    K Psi_ij = D^2 f [phi_i, phi_j] (central differences of ``force(u)``, the internal force at
    rest + u, (nv d,)); what a bent petal does besides bending (its tip drawn in), which linear
    modes alone can only do by stretching (the reduced model locks, too stiff at large bends)."""
    L = modes.shape[1]
    if L == 0:
        return np.zeros((X.size, 0))
    eps = 1e-3 * np.ptp(X, axis=0).max() / max(np.abs(modes).max(), 1e-300)
    loads = []
    for i in range(L):
        for j in range(i, L):
            a, b = eps * modes[:, i], eps * modes[:, j]
            loads.append((force(a + b) - force(a - b) - force(b - a) + force(-a - b)) / (4 * eps * eps))
    return static_responses(K, X, mass, np.stack(loads, 1)) if loads else np.zeros((X.size, 0))
