"""Cubature: the reduced internal force sum_e Phi_e^T f_e(X + Phi z) estimated from a few elements
with non-negative weights, chosen by greedy non-negative least squares on training poses (An, Kim
and James 2008, "Optimizing cubature for efficient integration of subspace deformations").
The element forces are the full model's own kernels (sdexp.sim.physics.reference.element_forces)
run over the elements' nodes as separate copies, so each element's force comes out on its own."""
from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from sdexp.sim.physics.fem import FemModel, element_data, kernels, rest_quaternions
from sdexp.sim.physics.reference import element_forces


class ElementForces:
    """Every element's nodal forces at given positions, their rotations warm-started from the
    previous call (poses in sequence converge in a few polar iterations)."""

    def __init__(self, fem: FemModel):
        self.fem = fem
        ne, n = fem.elems.shape
        self.elems = np.arange(ne * n, dtype=np.int32).reshape(ne, n)
        self.Bm, self.vol = element_data(fem, np.float64)
        self.kernel = kernels().linear_3d(np.float64)
        self.q = rest_quaternions(fem.n_rotations) if fem.dim == 3 else np.zeros((0, 4))
        self.fbuf = np.zeros((1, ne * n, fem.dim))

    def __call__(self, x: np.ndarray, iterations: int = 6) -> np.ndarray:
        """(ne, nodes, dim) nodal forces at positions x (nv, dim); each call runs the kernels'
        warm-started polar iteration ``iterations`` times (two steps each)."""
        f = self.fem
        xu = np.ascontiguousarray(x[f.elems].reshape(-1, f.dim))
        for _ in range(iterations):
            element_forces(self.kernel, xu, self.elems, self.Bm, self.vol, f.mu, f.lam, self.q, self.fbuf, np.float64)
        return self.fbuf[0].reshape(f.elems.shape + (f.dim,))


def reduced_element_forces(forces: ElementForces, Phi3: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(ne, r): each element's reduced force Phi_e^T f_e at positions x; Phi3 (nv, dim, r)."""
    fe = forces(x)
    return np.einsum("end,endr->er", fe, Phi3[forces.fem.elems], optimize=True)


def greedy_nnls(blocks: list[np.ndarray], budget: int, tolerance: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(elements, weights, relative error): ``blocks``, one (ne, r) matrix of per-element reduced
    forces a training pose, each scaled by its total's norm; elements added a few at a time where
    the residual points, non-negative weights refitted each round, until the residual is below
    ``tolerance`` of the totals or ``budget`` elements are used."""
    A = np.concatenate([b.T for b in blocks])                 # (S r, ne)
    b = A.sum(axis=1)
    norms = np.linalg.norm(A, axis=0) + 1e-300
    chosen: list[int] = []
    w = np.zeros(0)
    res = b.copy()
    bn = np.linalg.norm(b)
    batch = max(1, budget // 24)
    while len(chosen) < budget and np.linalg.norm(res) > tolerance * bn:
        score = (A.T @ res) / norms
        score[chosen] = -np.inf
        new = [int(e) for e in np.argsort(score)[::-1][:min(batch, budget - len(chosen))] if score[e] > 0]
        if not new:
            break
        chosen += new
        w, _ = nnls(A[:, chosen], b, maxiter=50 * len(chosen))
        keep = w > 0
        chosen = [e for e, k in zip(chosen, keep) if k]
        w = w[keep]
        res = b - A[:, chosen] @ w
    return np.array(chosen, dtype=np.int64), w, float(np.linalg.norm(res) / bn)
