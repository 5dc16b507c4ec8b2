"""sdexp's FEM against an independent implementation, scikit-fem (issue 25, item 5).

What is compared, on a structured beam (3D tets and 2D triangles, sdexp.eval.validate_fem's
``structured_beam``), the default flower (3D, fTetWild) and the default rod (2D), each with
linear and with quadratic elements:

* the stiffness at rest: ``sdexp.sim.physics.modes.stiffness(fem)`` against scikit-fem's
  ``linear_elasticity`` form assembled with ``ElementVector`` of P1 / P2 tets or triangles
  (Lame parameters from the config's E and nu by scikit-fem's ``lame_parameters``; 2D is plane
  strain per metre of depth in both), as the relative Frobenius norm and the largest entry of
  the difference over the largest entry of the reference;
* the lumped nodal masses ``fem.mass`` (HRZ for quadratic elements, equal shares for linear
  ones) against HRZ lumping written here from its definition (Hinton, Rock & Zienkiewicz 1976)
  and applied to scikit-fem's consistent element mass matrices, rho * int u.v: per element and
  per direction, the diagonal of the direction's block scaled so that it sums to the block's
  total (the element's mass); density = the config's mass over scikit-fem's integrated volume.
  For linear elements HRZ is the equal split sdexp uses. Compared node by node, relative to
  each node's mass, in every direction.

Why this is independent: the only inputs shared are the corner positions, the corner
connectivity and the config's E, nu and mass. scikit-fem makes its own edges and mid-edge
dofs, evaluates its reference-element basis through its own affine mapping at its own
quadrature (degree 2 x the element's: 4 for P2, where sdexp's stiffness uses the 4-point
degree-2 rule on barycentric gradients from Dm^-1), integrates the mass numerically (sdexp
uses the closed-form HRZ fractions 1/36, 4/27 | 1/19, 16/57 times rho V) and numbers its dofs its
own way: they are mapped onto sdexp's node-major dofs (node i's components at dim i + c) by
position (a k-d tree on the dof locations, each component read off the basis function itself),
so the check does not depend on either numbering. Both integrate exactly (polynomials within
the rules' degree), so the two agree to rounding: measured <= 3.5e-15 relative; the bound is
1e-12. ``test_the_crosscheck_sees_small_errors`` shows the comparison can fail: nu off by 1e-6
changes the stiffness by ~2e-6 relative, one node's mass off by 1e-9 is seen, and the other
common lumping (row sums) is far off for quadratic elements.
"""
import numpy as np
import pytest
import scipy.sparse as sp
import skfem
from scipy.spatial import cKDTree
from skfem.helpers import dot
from skfem.models.elasticity import lame_parameters, linear_elasticity

from sdexp.eval.validate_fem import Beam, structured_beam
from sdexp.sim.drone import build_drone
from sdexp.sim.physics.fem import build_fem
from sdexp.sim.physics.modes import stiffness
from sdexp.sim.physics.quadratic import quadratic_mesh
from tests.conftest import make_config

TOL = 1e-12   # relative; measured agreement is ~1e-15

ELEMENTS = {(3, 1): skfem.ElementTetP1, (3, 2): skfem.ElementTetP2,
            (2, 1): skfem.ElementTriP1, (2, 2): skfem.ElementTriP2}


@skfem.BilinearForm
def _mass(u, v, w):
    return dot(u, v)


@skfem.Functional
def _volume(w):
    return 1.0 + 0.0 * w.x[0]


def skfem_reference(points: np.ndarray, elems: np.ndarray, youngs_modulus: float,
                    poisson_ratio: float, total_mass: float) -> tuple[sp.csr_matrix, np.ndarray, sp.csr_matrix]:
    """scikit-fem's rest stiffness (n dim)^2, HRZ-lumped masses (n dim,) and consistent mass
    (n dim)^2 on the mesh that sdexp's nodes ``points`` and elements ``elems`` (linear or
    quadratic) describe, all in sdexp's node-major dof order. scikit-fem sees only the corners."""
    d = points.shape[1]
    order = 1 if elems.shape[1] == d + 1 else 2
    corner_ids, corner_elems = np.unique(elems[:, :d + 1], return_inverse=True)
    mesh = (skfem.MeshTet if d == 3 else skfem.MeshTri)(
        np.ascontiguousarray(points[corner_ids].T), np.ascontiguousarray(corner_elems.reshape(-1, d + 1).T))
    element = ELEMENTS[d, order]()
    basis = skfem.Basis(mesh, skfem.ElementVector(element))

    lam, mu = lame_parameters(youngs_modulus, poisson_ratio)
    K = linear_elasticity(lam, mu).assemble(basis)
    density = total_mass / _volume.assemble(skfem.Basis(mesh, element))
    elemental = _mass.elemental(basis)
    local = density * elemental.tolocal()                   # (ne, nbfun, nbfun) consistent masses

    # the component each local basis function moves: the one row of its value that is not zero
    comp = np.array([np.abs(np.asarray(phi[0])).sum(axis=(1, 2)).argmax() for phi in basis.basis])
    assert np.array_equal(np.bincount(comp), np.full(d, basis.Nbfun // d))
    hrz = np.zeros(basis.N)
    for c in range(d):
        idx = np.flatnonzero(comp == c)
        block = local[:, idx][:, :, idx]
        diag = np.einsum("eii->ei", block)
        share = diag * (block.sum(axis=(1, 2)) / diag.sum(axis=1))[:, None]
        np.add.at(hrz, basis.element_dofs[idx].T, share)

    # skfem's dofs onto sdexp's by position and component
    dof_comp = np.empty(basis.N, dtype=int)
    dof_comp[basis.element_dofs] = comp[:, None]
    dist, node = cKDTree(points).query(basis.doflocs.T)
    scale = np.ptp(points, axis=0).max()
    assert dist.max() < 1e-9 * scale, "a scikit-fem dof has no sdexp node at its location"
    target = node * d + dof_comp
    assert np.array_equal(np.sort(target), np.arange(len(points) * d)), "the dof map is not a bijection"
    P = sp.csr_matrix((np.ones(basis.N), (target, np.arange(basis.N))), shape=(basis.N, basis.N))
    masses = np.empty(basis.N)
    masses[target] = hrz
    return (P @ K @ P.T).tocsr(), masses, (P @ (density * elemental.tocsr()) @ P.T).tocsr()


def stiffness_difference(K: sp.spmatrix, reference: sp.spmatrix) -> tuple[float, float]:
    """(relative Frobenius norm, largest entry over the reference's largest) of K - reference."""
    D = (K - reference).tocsr()
    return (float(sp.linalg.norm(D) / sp.linalg.norm(reference)),
            float(abs(D).max() / abs(reference).max()))


def mass_difference(mass: np.ndarray, reference: np.ndarray, dim: int) -> float:
    """Largest |sdexp - reference| / |reference| over nodes and directions."""
    m = np.repeat(mass, dim)
    return float(np.max(np.abs(m - reference) / np.abs(reference)))


# ------------------------------------------------------------------------------ the models

def _beam(dim: int, element: str):
    beam = Beam()
    points, elems = structured_beam(beam, dim, 2)
    if element == "quadratic":
        points, elems = quadratic_mesh(points, elems)
    mass = 1.7
    return (build_fem(points, elems, mass, beam.youngs_modulus, beam.poisson_ratio),
            beam.youngs_modulus, beam.poisson_ratio, mass)


def _drone(name: str, element: str, cache_dir: str):
    cfg = make_config(f"drone={name}", f"cache_dir={cache_dir}")
    fem = build_drone(cfg.drone, cfg.cache_dir, element).fem
    return fem, cfg.drone.youngs_modulus, cfg.drone.poisson_ratio, cfg.drone.mass


CASES = [(m, e) for m in ("beam3d", "beam2d", "flower", "rod") for e in ("quadratic", "linear")]
_MODELS = {}


@pytest.fixture(params=CASES, ids=[f"{m}-{e}" for m, e in CASES])
def model(request, cache_dir):
    """(sdexp's FemModel, skfem_reference's (K, HRZ masses, M), the total mass) of one mesh with
    one element type, made once."""
    if request.param not in _MODELS:
        mesh, element = request.param
        fem, E, nu, mass = _beam(int(mesh[4]), element) if mesh.startswith("beam") else _drone(mesh, element, cache_dir)
        _MODELS[request.param] = fem, skfem_reference(fem.rest, fem.elems, E, nu, mass), mass
    return _MODELS[request.param]


# ------------------------------------------------------------------------------ the checks

def test_the_rest_stiffness_is_scikit_fems(model):
    fem, (K_ref, _, _), _ = model
    fro, top = stiffness_difference(stiffness(fem), K_ref)
    assert fro < TOL and top < TOL, f"relative difference: Frobenius {fro:.3g}, largest entry {top:.3g}"


def test_the_lumped_masses_are_hrz_of_scikit_fems_consistent_mass(model):
    fem, (_, m_ref, _), mass = model
    worst = mass_difference(fem.mass, m_ref, fem.dim)
    assert worst < TOL, f"largest relative nodal mass difference {worst:.3g}"
    assert np.isclose(m_ref.sum(), mass * fem.dim, rtol=TOL)   # every direction carries the mass


@pytest.mark.parametrize("dim", [3, 2])
def test_the_crosscheck_sees_small_errors(dim):
    """The comparison can fail: a Poisson ratio 1e-6 off, one node's mass 1e-9 off and
    row-sum lumping in place of HRZ are all far outside the tolerance."""
    fem, E, nu, mass = _beam(dim, "quadratic")
    K = stiffness(fem)
    K_off, m_ref, M = skfem_reference(fem.rest, fem.elems, E, nu + 1e-6, mass)
    fro, top = stiffness_difference(K, K_off)
    assert fro > 1e-7 and top > 1e-7, (fro, top)

    wrong = fem.mass.copy()
    wrong[len(wrong) // 2] *= 1 + 1e-9
    assert mass_difference(wrong, m_ref, dim) > 100 * TOL

    # row-sum lumping of the same consistent mass: a 10-node tet's corners get -1/20 of its mass
    row_sums = np.asarray(M.sum(axis=1)).ravel()
    assert mass_difference(fem.mass, row_sums, dim) > 0.1
