"""The body's linear modes at rest: the assembled stiffness, free-free frequencies, the largest
eigenvalue of M^-1 K that sets the stable explicit step, and targeted inertial mass scaling
(sim.mass_scaling), which lowers that eigenvalue by adding inertia where it lives.

Why targeted: the step is set by omega_max = sqrt(lambda_max(M^-1 K)); uniform mass scaling by s
buys sqrt(s) and changes every frequency by the same factor. The highest modes live on a few
nodes (small or badly shaped elements, the HRZ corner nodes), so inertia added there lowers
lambda_max while the low modes, which carry the drone's bending, barely move. Gravity keeps
pulling on the physical mass (integrator.Body's gravity_share): only inertia is added.
"""
from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sdexp.cache import cached_arrays, key_of
from sdexp.sim.physics.fem import FemModel
from sdexp.sim.physics.quadratic import EDGES_2D, EDGES_3D, QUAD_2D, QUAD_3D

log = logging.getLogger(__name__)

MASS_SCALING_FORMAT = 1   # the cached added masses: a change to the search below bumps this


def shape_gradients(fem: FemModel) -> tuple[np.ndarray, np.ndarray]:
    """Rest gradients of the shape functions at the quadrature points, (nq, ne, nodes, dim),
    and the points' weights (nq,), for linear (one point) or quadratic elements."""
    d = fem.dim
    grad = np.concatenate([-fem.Bm.sum(axis=1, keepdims=True), fem.Bm], axis=1)   # grad L_j (ne, d+1, d)
    if fem.order == 1:
        return grad[None], np.ones(1)
    rule, edges = (QUAD_3D, EDGES_3D) if d == 3 else (QUAD_2D, EDGES_2D)
    out = []
    for L in rule:
        corners = (4 * L - 1)[None, :, None] * grad
        mids = 4 * (L[edges[:, 0]][None, :, None] * grad[:, edges[:, 1]]
                    + L[edges[:, 1]][None, :, None] * grad[:, edges[:, 0]])
        out.append(np.concatenate([corners, mids], axis=1))
    return np.stack(out), np.full(len(rule), 1.0 / len(rule))


def stiffness(fem: FemModel, chunk: int = 4000) -> sp.csr_matrix:
    """The stiffness of linear elasticity at rest, (nv dim)^2: the linearisation of the
    co-rotated force at the rest shape (the rotation's derivative acts on zero stress there)."""
    G, w = shape_gradients(fem)
    d, n = fem.dim, fem.elems.shape[1]
    rows, cols, vals = [], [], []
    eye = np.eye(d)
    for e0 in range(0, fem.n_elems, chunk):
        sl = slice(e0, e0 + chunk)
        K = np.zeros((len(fem.vol[sl]), n, d, n, d))
        for g, wq in zip(G[:, sl], w):
            Vw = (wq * fem.vol[sl])[:, None, None, None, None]
            K += Vw * (fem.lam * np.einsum("eai,ebj->eaibj", g, g)
                       + fem.mu * np.einsum("eak,ebk,ij->eaibj", g, g, eye)
                       + fem.mu * np.einsum("eaj,ebi->eaibj", g, g))
        dof = (fem.elems[sl][:, :, None] * d + np.arange(d)).reshape(len(K), -1)
        rows.append(np.repeat(dof, n * d, axis=1).ravel())
        cols.append(np.tile(dof, (1, n * d)).ravel())
        vals.append(K.reshape(len(K), -1).ravel())
    size = len(fem.rest) * d
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))


def rigid_modes(x: np.ndarray) -> np.ndarray:
    """(nv dim, 6 | 3) translations and infinitesimal rotations about the centroid."""
    nv, d = x.shape
    r = x - x.mean(axis=0)
    if d == 2:
        return np.stack([np.tile([1.0, 0.0], nv), np.tile([0.0, 1.0], nv), np.c_[-r[:, 1], r[:, 0]].ravel()], 1)
    modes = [np.tile(e, nv) for e in np.eye(3)]
    for e in np.eye(3):
        modes.append(np.cross(e, r).ravel())
    return np.stack(modes, 1)




def _dofs(mass: np.ndarray, dim: int) -> np.ndarray:
    return np.repeat(np.asarray(mass, float), dim)


def top_modes(K: sp.csr_matrix, mass: np.ndarray, dim: int, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The k largest eigenvalues of M^-1 K (descending) and their mass-normalised shapes
    (nv dim, k), from the symmetric D K D with D = M^-1/2 (M the lumped, diagonal mass)."""
    d = 1.0 / np.sqrt(_dofs(mass, dim))
    A = sp.diags(d) @ K @ sp.diags(d)
    vals, vecs = spla.eigsh(A, k=k, which="LA", tol=1e-8)
    order = np.argsort(vals)[::-1]
    return vals[order], d[:, None] * vecs[:, order]


def free_frequencies(fem: FemModel, mass: np.ndarray | None = None, k: int = 8,
                     K: sp.csr_matrix | None = None) -> np.ndarray:
    """The first k free-free natural frequencies (Hz) of the body at rest, rigid motions left
    out."""
    return free_modes(fem, mass, k, K)[0]


def free_modes(fem: FemModel, mass: np.ndarray | None = None, k: int = 8,
               K: sp.csr_matrix | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The first k free-free natural frequencies (Hz) and their mass-normalised shapes (nv dim, k):
    K phi = omega^2 M phi by shift-invert just below zero (K - sigma M is then definite), the
    rigid motions left out."""
    d = fem.dim
    K = stiffness(fem) if K is None else K
    M = sp.diags(_dofs(fem.mass if mass is None else mass, d))
    rigid = 6 if d == 3 else 3
    vals, vecs = spla.eigsh(K.tocsc(), k=k + rigid, M=M.tocsc(), sigma=-1.0, which="LM")
    order = np.argsort(vals)[rigid:]
    return np.sqrt(np.maximum(vals[order], 0.0)) / (2 * np.pi), vecs[:, order]


def targeted_mass(fem: FemModel, budget: float, step: float = 0.05, modes: int = 24,
                  iterations: int = 40) -> tuple[np.ndarray, float]:
    """Inertia to add per node (nv,) so that lambda_max(M^-1 K) falls by the largest factor
    gain^2 (gain on a ladder of ``step``) whose added mass stays within ``budget`` x the body's
    mass; returns (added, gain), (zeros, 1.0) when no rung fits.

    Each round takes the ``modes`` highest modes still above the target lambda_0 / gain^2. For a
    mass-normalised mode phi, adding delta_i at node i lowers its Rayleigh quotient to
    lambda / (1 + sum delta_i |phi_i|^2); the inertia goes to the nodes in proportion to their
    share of the mode's kinetic energy (relative to the largest share, below a tenth none), scaled
    to bring that mode to the target; a node takes the largest demand of the modes it is in.
    Rounds repeat until no mode is above the target (adding inertia lets other modes surface);
    a rung that does not settle in ``iterations`` rounds, or passes the budget, ends the search."""
    d = fem.dim
    K = stiffness(fem)
    m = np.asarray(fem.mass, float)
    lam0 = top_modes(K, m, d)[0][0]
    added, best, gain = np.zeros_like(m), (np.zeros_like(m), 1.0), 1.0
    while True:
        gain = round(gain + step, 10)
        target = lam0 / gain ** 2
        for _ in range(iterations):
            vals, phi = top_modes(K, m + added, d, min(modes, len(m) * d - 2))
            above = vals > target * (1 + 1e-3)
            if not above.any():
                break
            demand = np.zeros_like(m)
            for lam, mode in zip(vals[above], phi[:, above].T):
                amp = np.sum(mode.reshape(-1, d) ** 2, axis=1)          # |phi_i|^2
                share = (m + added) * amp                                # kinetic-energy share, sums to 1
                weight = share / share.max()
                weight[weight < 0.1] = 0.0
                alpha = (lam / target - 1.0) / np.sum(weight * share)
                demand = np.maximum(demand, alpha * (m + added) * weight)
            added = added + demand
            if added.sum() > budget * m.sum():
                return best
        else:
            return best
        best = (added.copy(), gain)


def strain_energy(fem: FemModel, x: np.ndarray) -> float:
    """The co-rotated elastic energy of positions x (J): sum over quadrature points of
    w V (mu |eps|^2 + lam / 2 tr(eps)^2), eps = sym(R^T F) - I with R the exact polar rotation
    (SVD): what the kernels' forces are the gradient of, up to the warm-started R."""
    G, w = shape_gradients(fem)
    X = x[fem.elems]                                        # (ne, nodes, dim)
    energy = 0.0
    for g, wq in zip(G, w):
        F = np.einsum("eai,eaj->eij", X, g)
        U, _, Vt = np.linalg.svd(F)
        flip = np.linalg.det(U @ Vt) < 0
        U[flip, :, -1] *= -1
        R = U @ Vt
        S = np.einsum("eki,ekj->eij", R, F)
        eps = 0.5 * (S + np.swapaxes(S, 1, 2)) - np.eye(fem.dim)
        tr = np.trace(eps, axis1=1, axis2=2)
        energy += float(np.sum(wq * fem.vol * (fem.mu * np.sum(eps * eps, axis=(1, 2)) + 0.5 * fem.lam * tr * tr)))
    return energy


@dataclass(frozen=True)
class MassScaling:
    """sim.mass_scaling's outcome for one model: ``added`` (nv,) inertia, None when unscaled;
    ``gain``, the factor on lambda_max^-1/2 (the stable step) it buys; ``fraction``, the added
    mass over the body's."""
    added: np.ndarray | None
    gain: float
    fraction: float


def mass_scaling(fem: FemModel, budget: float, cache_dir) -> MassScaling:
    """targeted_mass for ``fem`` within ``budget``, computed once per model (its arrays' hash:
    the mesh, the material and what effects changed) and cached under ``cache_dir``."""
    if budget <= 0:
        return MassScaling(None, 1.0, 0.0)
    h = hashlib.sha256()
    for a in (fem.rest, fem.elems, fem.mass, np.array([fem.mu, fem.lam])):
        h.update(np.ascontiguousarray(a).tobytes())
    key = key_of("massscale", MASS_SCALING_FORMAT, {"fem": h.hexdigest(), "budget": float(budget)})

    def make() -> dict:
        added, gain = targeted_mass(fem, budget)
        return {"added": added, "gain": np.array(gain)}
    a = cached_arrays(cache_dir, key, make)
    gain = float(a["gain"])
    if gain <= 1.0:
        return MassScaling(None, 1.0, 0.0)
    return MassScaling(a["added"], gain, float(a["added"].sum() / fem.mass.sum()))
