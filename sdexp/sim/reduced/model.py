"""The reduced model of one drone: built from its full FEM (snapshots, basis, cubature), cached,
and the quantities the reduced step needs (sdexp.sim.reduced.body), all in three dimensions (a 2D
drone's positions get a zero z and it turns about z only).

Equations (Kane's method with generalised speeds: the centre of mass's velocity v (world), the
body-frame angular velocity w and the modal velocities zd), for x_i = c + R rho_i,
rho_i = X_i + Phi_i z, Phi mass-orthonormal and mass-orthogonal to the rigid motions at rest:
  M dv/dt = R F_body + F_world - M g y
  I(z) dw/dt + B(z) zdd = tau - w x I w - 2 (w tr W - W w)
  B(z)^T dw/dt + zdd    = f_z - (w w^T - |w|^2) : (P + T(z)) - 2 w . vec(T'(zd)^T)
with S(z) = sum m rho rho^T, I = tr S - S, B_l = sum m rho x Phi_l, W = sum m (Phi zd) rho^T, all
polynomials in z of the precomputed tensors P_j = sum m Phi_j X^T and Q_jl = sum m Phi_j Phi_l^T
(T(z)_j = sum_l Q_jl z_l): no sum over the nodes in the step. The internal force f_z is the
cubature's; its net force and torque are zero in the full model, so only f_z enters.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from sdexp.cache import cached_arrays, content_digest, key_of
from sdexp.errors import UserError
from sdexp.sim.drone import Drone
from sdexp.sim.physics.fem import FemModel, elastic_forces, rest_quaternions
from sdexp.sim.physics.modes import free_modes, stiffness
from sdexp.sim.reduced.basis import (best_fit_frame, centred_rest, deformation_basis, deformations, modal_derivatives,
                                    static_responses)
from sdexp.sim.reduced.cubature import ElementForces, greedy_nnls, reduced_element_forces
from sdexp.sim.reduced.snapshots import NEAR_HOVER, PAPER, flights

log = logging.getLogger(__name__)

REDUCED_FORMAT = 6   # bump when what build_reduced makes changes
POSES = 200          # flight poses the cubature is fitted on


@dataclass(frozen=True)
class ReducedSpec:
    """sim.reduced, as plain values (sdexp.config.ReducedConfig is the user's side, with the same
    defaults and what each means)."""
    basis: int = 64
    linear_modes: int = 12
    cubature: int = 200
    tolerance: float = 0.01
    snapshot_seconds: float = 40.0
    range_margin: float = 1.5
    seed: int = 0
    rotor_statics: bool = True
    modal_derivatives: int = 4
    exact_modes: bool = True


def spec_of(cfg) -> ReducedSpec:
    """sim.reduced (a ReducedConfig or anything with its fields) as a ReducedSpec."""
    return ReducedSpec(int(cfg.basis), int(cfg.linear_modes), int(cfg.cubature), float(cfg.tolerance),
                       float(cfg.snapshot_seconds), float(cfg.range_margin), rotor_statics=bool(cfg.rotor_statics),
                       modal_derivatives=int(cfg.modal_derivatives), exact_modes=bool(cfg.exact_modes))


def pad3(a: np.ndarray) -> np.ndarray:
    """(n, d) rows as (n, 3), a zero z for 2D."""
    return a if a.shape[1] == 3 else np.c_[a, np.zeros(len(a))]


def build_reduced(drone: Drone, spec: ReducedSpec, cache_dir: str, gravity: float = 9.81,
                  control_dt: float = 0.01) -> "ReducedModel":
    """The drone's reduced model, from the cache or made (a logged phase, with its time)."""
    fem = drone.fem
    if spec.basis > fem.rest.size - (6 if fem.dim == 3 else 3):
        raise UserError(f"sim.reduced.basis = {spec.basis}: drone {drone.name} has only "
                        f"{fem.rest.size - (6 if fem.dim == 3 else 3)} deformation degrees of freedom")
    # range_margin and exact_modes are read at load, not built: they share one entry
    built = replace(spec, range_margin=1.0, exact_modes=ReducedSpec.exact_modes)
    key = key_of("reduced", REDUCED_FORMAT, content_digest(fem, drone.rotors, drone.max_thrust, drone.damping,
                                                          drone.deformation_damping, built,
                                                          float(gravity), float(control_dt)))

    def make() -> dict[str, np.ndarray]:
        from sdexp.log import Phase
        with Phase(f"building the reduced model of {drone.name} ({spec.basis} basis vectors, up to "
                   f"{spec.cubature} cubature elements)") as phase:
            t0 = time.perf_counter()
            made = _make(drone, spec, gravity, control_dt)
            made["build_seconds"] = np.array(time.perf_counter() - t0)
            phase.close(f"{len(made['elements'])} elements, force error {float(made['cubature_error']):.3f}, "
                        f"{float(made['captured']):.4f} of the snapshots' deformation held, "
                        f"{float(made['build_seconds']):.0f} s")
        return made

    return ReducedModel(drone, cached_arrays(cache_dir, key, make), spec)


def _internal_force(fem: FemModel):
    """u (nv d,) -> the full model's internal force at rest + u (nv d,), rotations converged."""
    def force(u: np.ndarray) -> np.ndarray:
        q = rest_quaternions(fem.n_rotations) if fem.dim == 3 else None
        x = fem.rest + u.reshape(fem.rest.shape)
        for _ in range(4):
            f = elastic_forces(fem, x, q)
        return f.ravel()
    return force


def centrifugal_loads(X: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """(nv d, 6 | 3): the loads m_i S X_i of the symmetric matrices S that span the centrifugal
    field w x (w x X) = (w w^T - |w|^2) X of any spin."""
    d = X.shape[1]
    out = []
    for a in range(d):
        for b in range(a, d):
            S = np.zeros((d, d))
            S[a, b] = S[b, a] = 1.0
            out.append((mass[:, None] * (X @ S.T)).ravel())
    return np.stack(out, 1)


def rotor_loads(drone: Drone) -> np.ndarray:
    """(nv d, m): each rotor's unit thrust on its patch along its design normal, at rest."""
    rot, d = drone.rotors, drone.dim
    out = np.zeros((drone.fem.rest.size, rot.count))
    for k in range(rot.count):
        for j in range(rot.vert_ptr[k], rot.vert_ptr[k + 1]):
            out[d * rot.verts[j]:d * rot.verts[j] + d, k] += rot.weights[j] * rot.normals[k]
    return out


def _make(drone: Drone, spec: ReducedSpec, gravity: float, control_dt: float) -> dict[str, np.ndarray]:
    fem = drone.fem
    mass = fem.mass
    X, _ = centred_rest(fem.rest, mass)
    half = spec.snapshot_seconds / 2
    t0 = time.perf_counter()
    xs = np.concatenate([flights(drone, NEAR_HOVER, half, spec.seed, gravity, control_dt),
                         flights(drone, PAPER, half, spec.seed + 1, gravity, control_dt)])
    log.info(f"reduced model of {drone.name}: {len(xs)} snapshots in {time.perf_counter() - t0:.1f} s")
    U = deformations(xs, X, mass)
    L = min(spec.linear_modes, spec.basis)
    K = stiffness(fem)
    _, modes = free_modes(fem, k=max(L, 1), K=K)
    # each rotor's and each spin's quasi-static response: the local bending under a patch and the
    # centrifugal stretch that the snapshots' principal components hold in the mass norm but a
    # Galerkin model needs in its own span (without them a spinning plate stretches 20% too little)
    loads = np.c_[rotor_loads(drone), centrifugal_loads(X, mass)]
    statics = static_responses(K, X, mass, loads) if spec.rotor_statics else np.zeros((X.size, 0))
    derivs = modal_derivatives(K, X, mass, modes[:, :spec.modal_derivatives], _internal_force(fem))
    Phi, captured = deformation_basis(X, mass, np.c_[modes[:, :L], statics, derivs], U, spec.basis)
    r = Phi.shape[1]
    m = np.repeat(mass, fem.dim)
    Z = (Phi.T @ (m[:, None] * U.reshape(len(U), -1).T)).T          # (S, r): the snapshots' coordinates
    Phi3 = Phi.reshape(len(X), fem.dim, r)
    # The cubature is fitted on two things: the co-rotation's nonlinear remainder g(z) = f(z) + K_r z of
    # the flight poses (what the rotations add to linear elasticity; fitting f itself let the linear
    # part, large in a folded petal, drown it) and the linear force of small motions along every basis
    # vector (the rest stiffness K_r = Phi^T K Phi: the frequencies and the stable step). Together the
    # cubature's force approximates f = -K_r z + g. (Replacing the cubature's rest stiffness by the
    # exact one in the step instead, a linear correction, made the frequencies exact but broke large
    # deformations: on the star it diverged within 0.4 s of a hover flight, 127% off, 3.8% without it.)
    forces, linear = ElementForces(fem), ElementForces(fem)
    amp = 1e-4 * np.ptp(X, axis=0).max()
    blocks = []
    for z in Z[:: max(1, len(Z) // POSES)]:
        u = (Phi @ z).reshape(X.shape)
        scale = amp / max(np.abs(u).max(), 1e-300)
        g = (reduced_element_forces(forces, Phi3, X + u)
             - reduced_element_forces(linear, Phi3, X + scale * u) / scale)   # the remainder g_e
        blocks.append(g / (np.linalg.norm(g.sum(axis=0)) + 1e-300))
    # and small motions along every basis vector, weighted as much as the flight poses together: a
    # cubature free to miss the rest stiffness picks a few heavy elements that stiffen as they turn
    weight = np.sqrt(len(blocks) / r)
    for j in range(r):
        g = reduced_element_forces(linear, Phi3, X + amp * Phi3[:, :, j])
        blocks.append(weight * g / (np.linalg.norm(g.sum(axis=0)) + 1e-300))
    log.info(f"reduced model of {drone.name}: basis and {len(blocks)} training poses at {time.perf_counter() - t0:.1f} s")
    elements, weights, err = greedy_nnls(blocks, spec.cubature, spec.tolerance)
    log.info(f"reduced model of {drone.name}: cubature at {time.perf_counter() - t0:.1f} s")
    return {"Phi": Phi, "elements": elements, "weights": weights, "z_lo": Z.min(axis=0), "z_hi": Z.max(axis=0),
            "cubature_error": np.array(err), "captured": np.array(captured)}


class ReducedModel:
    """The arrays of one drone's reduced model and what the step reads, derived at load."""

    def __init__(self, drone: Drone, arrays: dict[str, np.ndarray], spec: ReducedSpec):
        fem = drone.fem
        self.drone, self.spec, self.dim = drone, spec, fem.dim
        self.Phi = np.ascontiguousarray(arrays["Phi"])
        self.r = r = self.Phi.shape[1]
        self.X, self.com = centred_rest(fem.rest, fem.mass)
        self.total_mass = float(fem.mass.sum())
        self.elements, self.weights = arrays["elements"], arrays["weights"]
        self.cubature_error = float(arrays["cubature_error"])
        self.build_seconds = float(arrays["build_seconds"])
        # the validated range: the snapshots' range of each coordinate x range_margin, at least a tenth
        # of the widest one's (the principal components' tail spans next to nothing in the snapshots,
        # and the stiff bunny's left it in one step of an ordinary flight)
        span = arrays["z_hi"] - arrays["z_lo"]
        span = np.maximum(span, 0.1 * span.max())
        mid = 0.5 * (arrays["z_hi"] + arrays["z_lo"])
        self.z_lo = mid - 0.5 * spec.range_margin * span
        self.z_hi = mid + 0.5 * spec.range_margin * span
        d = fem.dim
        Phi3 = self.Phi.reshape(len(self.X), d, r)
        P3 = np.zeros((len(self.X), 3, r))
        P3[:, :d] = Phi3
        self.Phi3 = P3
        self.X3 = X3 = pad3(self.X)   # rest rows in 3D (a zero z for 2D), as the step reads them
        m = fem.mass
        self.S0 = (m[:, None] * X3).T @ X3
        self.P = np.einsum("i,iaj,ib->jab", m, P3, X3)                           # (r, 3, 3)
        A = P3.reshape(len(m), 3 * r)
        G = (A * m[:, None]).T @ A                                               # (3 r, 3 r)
        # Q[(j, a, b), l] = sum m Phi_ja Phi_lb: (Q @ z)[j] = sum m Phi_j (Phi z)^T, one product a substep
        self.Q = np.ascontiguousarray(G.reshape(3, r, 3, r).transpose(1, 0, 2, 3).reshape(r * 9, r))
        self.a = np.einsum("i,ia,ibl->lab", m, X3, P3)                           # (r, 3, 3): sum m X_a Phi_lb
        # the cubature's sub-mesh: its elements, their nodes renumbered, the weights in the volumes
        el = fem.elems[self.elements]
        self.cub_nodes, local = np.unique(el, return_inverse=True)
        self.cub_elems = np.ascontiguousarray(local.reshape(el.shape).astype(np.int32))
        self.cub_Bm = np.ascontiguousarray(fem.Bm[self.elements])
        self.cub_vol = np.ascontiguousarray(fem.vol[self.elements] * self.weights)
        self.cub_X = np.ascontiguousarray(self.X[self.cub_nodes])
        self.cub_Phi = np.ascontiguousarray(Phi3[self.cub_nodes].reshape(-1, r))  # (nc d, r)
        # the rotors' and IMUs' nodes, renumbered into compact sets
        rot = drone.rotors
        self.rot_nodes, inv = np.unique(np.r_[rot.faces.ravel(), rot.verts], return_inverse=True)
        self.rot_faces = np.ascontiguousarray(inv[:rot.faces.size].reshape(rot.faces.shape))
        self.rot_verts = np.ascontiguousarray(inv[rot.faces.size:])
        self.rot_X = np.ascontiguousarray(X3[self.rot_nodes])
        self.rot_Phi = np.ascontiguousarray(P3[self.rot_nodes].reshape(-1, r))   # (nr 3, r)
        imus = drone.imus
        self.imu_nodes, inv = np.unique(imus.idx, return_inverse=True)
        self.imu_idx = inv.reshape(imus.idx.shape)
        self.imu_X = np.ascontiguousarray(X3[self.imu_nodes])
        self.imu_Phi = np.ascontiguousarray(P3[self.imu_nodes].reshape(-1, r))
        self.stiffness_fix = self._stiffness_fix(fem) if spec.exact_modes else np.zeros((0, 0))

    def _stiffness_fix(self, fem: FemModel) -> np.ndarray:
        """(L, L): K_cub - K_exact of the rest stiffness among the first L basis vectors (the linear
        modes), added to the cubature's force as a linear term in their coordinates, so that the low
        frequencies are the full model's (the cubature's weights leave them 1-11% off). Only that
        block: the same correction over the whole basis broke large deformations (the star's hover
        flight diverged), its stiff principal components turning with the petals; 12 x 12 leaves
        the linear modes' coordinates, which stay small where the body folds, and bring the first 8
        frequencies within 0.03% on the flower."""
        L = min(self.spec.linear_modes, self.r)
        if L == 0:
            return np.zeros((0, 0))
        sub = FemModel(fem.dim, self.cub_X, self.cub_elems, self.cub_Bm, self.cub_vol, np.ones(len(self.cub_X)),
                       fem.mu, fem.lam)
        Pc, Pf = self.cub_Phi[:, :L], self.Phi[:, :L]
        return Pc.T @ (stiffness(sub) @ Pc) - Pf.T @ (stiffness(fem) @ Pf)

    def frame_and_coordinates(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(c, R, z) of full positions x (nv, dim): the best-fit frame and the mass-projected
        deformation (what a full state is as a reduced one)."""
        c, R = best_fit_frame(x, self.X, self.drone.fem.mass)
        u = ((x - c) @ R - self.X).ravel()
        m = np.repeat(self.drone.fem.mass, self.dim)
        return c, R, self.Phi.T @ (m * u)
