"""Co-rotated linear elasticity (Mueller & Gross 2004) on tets (3D) and triangles (2D), linear
here, quadratic in sdexp.sim.physics.quadratic (``FemModel.order`` tells which a model has).

The element force is the linear-elastic force in the element's rotated frame: with
F = Ds Dm^-1, R = polar(F), eps = sym(R^T F) - I and P = R (2 mu eps + lam tr(eps) I),
the nodal forces are -V P Dm^-T. This is the warped-stiffness force -R K (R^T x - X) of the
paper's simulator, written in stress form (fewer flops than the 12x12 matrix).

Rotations come from the warm-started quaternion iteration of Mueller et al. 2016 ("A robust
method to extract the rotational part of deformations"): it stays a proper rotation for
inverted elements and, warm-started from the last substep, needs one or two iterations.

2D uses plane strain with an out-of-plane depth of 1 m; the rotation is exact.

This module builds the model (FemModel), picks the kernels that run (compiled or numba) and
computes forces outside the step; the kernels are forces.h (compiled) and
sdexp.sim.physics.reference (their numba twin, in the same order and with the same names).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sdexp.cache import content_digest
from sdexp.sim.physics.native import library
from sdexp.sim.physics.reference import corotated_forces_3d, corotated_forces_3d_f32, element_forces


@dataclass
class FemModel:
    dim: int
    rest: np.ndarray      # (nv, dim) rest positions (quadratic: corners, then mid-edge nodes)
    elems: np.ndarray     # (ne, dim+1) int32, positively oriented; quadratic (ne, 10 | 6)
    Bm: np.ndarray        # (ne, dim, dim) inverse rest edge matrix Dm^-1 of the corners
    vol: np.ndarray       # (ne,) rest volume (2D: area x 1 m depth)
    mass: np.ndarray      # (nv,) lumped mass
    mu: float
    lam: float

    @property
    def n_elems(self) -> int:
        return len(self.elems)

    @property
    def order(self) -> int:
        """1 for linear elements, 2 for quadratic ones."""
        return 1 if self.elems.shape[1] == self.dim + 1 else 2

    @property
    def n_rotations(self) -> int:
        """Warm-start quaternions the 3D kernels keep: one per element, or one per quadrature
        point of a quadratic tet."""
        return self.n_elems * (4 if self.order == 2 else 1)


def lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(mu, lambda); the same formulas serve 3D and 2D plane strain."""
    E, nu = youngs_modulus, poisson_ratio
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def signed_volumes(points: np.ndarray, elems: np.ndarray) -> np.ndarray:
    d = points.shape[1]
    D = np.stack([points[elems[:, k + 1]] - points[elems[:, 0]] for k in range(d)], axis=-1)
    return np.linalg.det(D) / (6.0 if d == 3 else 2.0)


def build_fem(rest: np.ndarray, elems: np.ndarray, total_mass: float,
              youngs_modulus: float, poisson_ratio: float) -> FemModel:
    """Precompute rest quantities. Linear elements (ne, dim+1): mass lumped evenly to the
    vertices. Quadratic ones (ne, 10 | 6, quadratic.quadratic_mesh): HRZ-lumped."""
    from sdexp.sim.physics.quadratic import lumped_mass, nodes_per_element

    rest = np.ascontiguousarray(rest, dtype=np.float64)
    elems = np.ascontiguousarray(elems, dtype=np.int32)
    d = rest.shape[1]
    if elems.shape[1] not in (nodes_per_element(d, 1), nodes_per_element(d, 2)):
        raise ValueError(f"{d}D elements need {nodes_per_element(d, 1)} or {nodes_per_element(d, 2)} "
                         f"nodes, not {elems.shape[1]}")
    Dm = np.stack([rest[elems[:, k + 1]] - rest[elems[:, 0]] for k in range(d)], axis=-1)
    vol = np.linalg.det(Dm) / (6.0 if d == 3 else 2.0)
    if np.any(vol <= 0):
        raise ValueError(f"{int(np.sum(vol <= 0))} elements are inverted or degenerate at rest")
    Bm = np.ascontiguousarray(np.linalg.inv(Dm))
    density = total_mass / vol.sum()
    if elems.shape[1] == d + 1:
        mass = np.zeros(len(rest))
        np.add.at(mass, elems.ravel(), np.repeat(density * vol / (d + 1), d + 1))
    else:
        mass = lumped_mass(len(rest), elems, density * vol)
    if np.any(mass <= 0):
        raise ValueError("mesh has vertices that belong to no element")
    mu, lam = lame(youngs_modulus, poisson_ratio)
    return FemModel(d, rest, elems, Bm, vol, mass, mu, lam)


@dataclass(frozen=True)
class Kernels:
    """The kernels that run: ``library``, the compiled kernels.c (sdexp.sim.physics.native) whose
    ``advance`` steps a whole Body, or None where it cannot be built; ``forces_3d``, the linear 3D
    force kernel with kernels.c's C signature (the compiled one, or else the numba cfunc) for
    the numba step and for elastic_forces; ``forces_3d_f32`` the same in float32."""
    library: object
    forces_3d: object
    forces_3d_f32: object

    def linear_3d(self, real):
        """The linear 3D force kernel in ``real`` (np.float64 | np.float32) arithmetic."""
        return self.forces_3d_f32 if real is np.float32 else self.forces_3d


def kernels() -> Kernels:
    """The one place that picks compiled or numba kernels (the library is built and loaded once
    per process, and logs which it is)."""
    lib = library()
    if lib is None:
        return Kernels(None, corotated_forces_3d.ctypes, corotated_forces_3d_f32.ctypes)
    return Kernels(lib, lib.corotated_forces_3d, lib.corotated_forces_3d_f32)


PRECISIONS = {"float64": np.float64, "float32": np.float32}   # sim.precision: the force arithmetic


def element_data(model: FemModel, real) -> tuple[np.ndarray, np.ndarray]:
    """(Bm, vol) in the force kernels' type ``real``: rounded once, not every substep."""
    return np.ascontiguousarray(model.Bm, dtype=real), np.ascontiguousarray(model.vol, dtype=real)


def elastic_forces(model: FemModel, x: np.ndarray, q: np.ndarray | None = None,
                   kernel=None, real=np.float64) -> np.ndarray:
    """Total elastic force on every vertex (nv, dim), for tests and the stability estimate
    (the simulator's loop fuses this with integration). ``q``: warm-start quaternions
    (model.n_rotations, 4) of type ``real``, updated. ``kernel``: a C-signature linear 3D kernel,
    by default the compiled one; quadratic elements use the numba reference (forces.h runs
    them in the step). ``real``: the arithmetic (sim.precision)."""
    fbuf = np.zeros((1,) + x.shape)
    if model.dim == 3:
        q = rest_quaternions(model.n_rotations).astype(real) if q is None else q
    Bm, vol = element_data(model, real)
    element_forces(kernel or kernels().linear_3d(real), x, model.elems, Bm, vol,
                   model.mu, model.lam, q if model.dim == 3 else np.zeros((0, 4), real), fbuf, real)
    return fbuf[0]


def rest_quaternions(n: int) -> np.ndarray:
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    return q


_STABLE: dict[str, float] = {}   # content digest -> step: one power iteration per body and process


def stable_substep(model: FemModel, safety: float, iterations: int = 60, seed: int = 0,
                   mass: np.ndarray | None = None) -> float:
    """safety x 2 / omega_max, omega_max^2 = largest eigenvalue of M^-1 K at rest (power
    iteration on the linearised force). Symplectic Euler is stable below 2 / omega_max.
    ``mass``: the inertial mass where it is not model.mass (sim.mass_scaling). Remembered per
    model content within the process: a fleet job builds dozens of simulators of one body (its
    data, open-loop holds, flights), each of which would repeat these 60 force evaluations (the
    tripod's: 1.3 s a simulator on a 2-core VM, 34 s of the reduced fleet test's 220)."""
    mass = model.mass if mass is None else mass
    key = content_digest(model, mass, float(safety), int(iterations), int(seed))
    if key not in _STABLE:
        _STABLE[key] = _power_iteration(model, mass, float(safety), iterations, seed)
    return _STABLE[key]


def _power_iteration(model: FemModel, mass: np.ndarray, safety: float, iterations: int, seed: int) -> float:
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(model.rest.shape)
    lam_max = 0.0
    eps = 1e-6 * np.ptp(model.rest, axis=0).max()
    for _ in range(iterations):
        u /= np.linalg.norm(u)
        Ku = -elastic_forces(model, model.rest + eps * u) / eps
        w = Ku / mass[:, None]
        lam_max = float(np.sum(u * w))
        u = w
    return safety * 2.0 / np.sqrt(1.05 * lam_max)  # 5% margin on the power-iteration estimate
