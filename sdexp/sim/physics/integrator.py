"""The explicit substep: elastic forces, rotor thrust, gravity, mass-proportional damping (of the
vertex velocities and of their deformation part), symplectic Euler, contact with the ground and
static boxes. ``Body`` holds the state arrays and runs whole control steps in compiled code
(kernels.c's ``advance``), or where no compiler works in its numba reference
(sdexp.sim.physics.reference, which also holds the step's arithmetic in Python form).
"""
from __future__ import annotations

import ctypes

import numba as nb
import numpy as np

from sdexp.sim.physics.fem import PRECISIONS, FemModel, element_data, kernels, rest_quaternions
from sdexp.sim.physics.native import Step, blocked
from sdexp.sim.physics.reference import advance


@nb.njit(cache=True)
def extent(x):
    """Largest side of the axis-aligned bounding box of x (n, dim); NaN if x is not finite.
    (NumPy's min/max over axis 0 of an (n, 3) array take ~80 us for the flower: 3% of a step.)"""
    lo = x[0].copy()
    hi = x[0].copy()
    for i in range(x.shape[0]):
        for c in range(x.shape[1]):
            a = x[i, c]
            if not np.isfinite(a):
                return np.nan
            lo[c] = min(lo[c], a)
            hi[c] = max(hi[c], a)
    return np.max(hi - lo)


_NO_ROTORS = (np.zeros(1, np.int64), np.zeros((0, 3), np.int64), np.zeros(1, np.int64),
              np.zeros(0, np.int64), np.zeros(0))


class Body:
    """The mutable state of one FEM body and the call that advances it. The state arrays (x, v,
    q, fext) are updated in place and must stay the same arrays: the compiled step holds
    pointers to them (checked at every ``run``). q is the compiled 3D step's blocked layout
    there: set and read it through ``set_rotation`` and ``quaternions``.

    ``threads`` sets how many force buffers (and threads) the element loop uses. ``precision``
    (sim.precision): the elastic forces' arithmetic, float64 or float32; the state (x, v) and
    the force sums stay float64, the element data and q are kept in the precision's type.
    ``added_mass`` (nv,): inertia added to the lumped mass (sim.mass_scaling); gravity keeps
    pulling on fem.mass."""

    def __init__(self, fem: FemModel, threads: int = 1, rotors=None, ground: float | None = None,
                 boxes_min=None, boxes_max=None, friction: float = 0.0, pinned=None,
                 compiled: bool = True, precision: str = "float64", added_mass=None):
        d = fem.dim
        self.fem = fem
        self.real = PRECISIONS[precision]
        self.x = fem.rest.copy()
        self.v = np.zeros_like(self.x)
        self.q = rest_quaternions(fem.n_rotations).astype(self.real) if d == 3 else np.zeros((0, 4), self.real)
        self.fbuf = np.zeros((threads,) + self.x.shape)
        self.mass = fem.mass if added_mass is None else fem.mass + added_mass   # inertial
        self.gravity_share = fem.mass / self.mass
        self.minv = 1.0 / self.mass
        if pinned is not None:
            self.minv[pinned] = 0.0
        self.ext = np.zeros_like(self.x)
        self.fext = np.zeros_like(self.x)   # effects' external forces (sdexp.sim.physics.effects)
        m = 0 if rotors is None else rotors.count
        self.dirs = np.zeros((m, d))
        self.rotors = _NO_ROTORS if rotors is None else (
            rotors.face_ptr, rotors.faces, rotors.vert_ptr, rotors.verts, rotors.weights)
        self.ground = -np.inf if ground is None else float(ground)
        self.boxes_min = np.zeros((0, d)) if boxes_min is None else np.asarray(boxes_min, float).reshape(-1, d)
        self.boxes_max = np.zeros((0, d)) if boxes_max is None else np.asarray(boxes_max, float).reshape(-1, d)
        self.friction = friction
        self.thrust = np.zeros(m)
        self._kernels = kernels()
        self._lib = self._kernels.library if compiled else None   # compiled=False: the numba reference step
        self._elements = (fem.elems, *element_data(fem, self.real))
        if d == 3 and self._lib is not None:
            self.q, self._elements = self._blocked()
        self._step = self._bind() if self._lib is not None else None

    def _blocked(self):
        """q and (el, Bm, vol) in the blocks of SIMD lanes the compiled 3D step reads in place
        (kernels.c, forces_impl / p2_forces_blocked); el padded with vertex 0, q with the
        identity (a quadratic tet's row holds its quadrature points' quaternions side by side).
        Quadratic tets' el is blocked too, (nb, 10, B): their node offsets are read in SIMD gathers."""
        f, b = self.fem, self._lib.block_size()
        per = f.n_rotations // f.n_elems
        q = blocked(self.q.reshape(f.n_elems, 4 * per), b, pad=np.tile([1.0, 0.0, 0.0, 0.0], per))
        el = np.zeros((q.shape[0] * b, f.elems.shape[1]), np.int32)
        el[:f.n_elems] = f.elems
        _, Bm, vol = self._elements
        if f.elems.shape[1] == 10:
            el = blocked(el, b)
        return q, (el, blocked(Bm.reshape(f.n_elems, 9), b), blocked(vol, b))

    def set_rotation(self, q) -> None:
        """Every element's warm-start rotation to the quaternion q (w, x, y, z)."""
        if self.q.ndim == 3:
            self.q[:] = np.tile(np.asarray(q, float), self.q.shape[1] // 4)[None, :, None]
        else:
            self.q[:] = q

    def quaternions(self) -> np.ndarray:
        """The warm-start rotations, (fem.n_rotations, 4), whatever the layout."""
        if self.q.ndim == 2:
            return self.q
        return np.moveaxis(self.q, -1, 1).reshape(-1, 4)[:self.fem.n_rotations]

    def _bind(self) -> Step:
        f, d = self.fem, self.fem.dim
        el, Bm, vol = self._elements
        arrays = dict(x=self.x, v=self.v, q=self.q, fbuf=self.fbuf, ext=self.ext, dirs=self.dirs,
                      fext=self.fext, minv=self.minv, mass=self.mass, Bm=Bm, vol=vol,
                      boxes_min=self.boxes_min, boxes_max=self.boxes_max, weights=self.rotors[4],
                      thrust=self.thrust, gravity_share=self.gravity_share, el=el, face_ptr=self.rotors[0],
                      faces=self.rotors[1], vert_ptr=self.rotors[2], verts=self.rotors[3])
        want = {"el": np.int32, "face_ptr": np.int64, "faces": np.int64, "vert_ptr": np.int64, "verts": np.int64,
                "q": self.real, "Bm": self.real, "vol": self.real}
        for name, a in arrays.items():
            if not (a.flags.c_contiguous and a.dtype == want.get(name, np.float64)):
                raise TypeError(f"Body.{name}: needs a C-contiguous {np.dtype(want.get(name, np.float64))} array")
        return Step(dim=d, nv=len(self.x), ne=f.n_elems, nt=self.fbuf.shape[0], n_rotors=len(self.dirs),
                    nodes=f.elems.shape[1], single=int(self.real is np.float32),
                    n_boxes=len(self.boxes_min), mu=f.mu, lam=f.lam, ground=max(self.ground, -1e300),
                    friction=self.friction, **{k: a.ctypes.data for k, a in arrays.items()})

    def forces_only(self, reps: int) -> None:
        """The elastic forces alone, ``reps`` times on one thread into fbuf[0] (the benchmark's
        kernel timing: sdexp.eval.bench_variants); the compiled step only."""
        if self._step is None:
            raise RuntimeError("Body.forces_only: needs the compiled kernels")
        self._lib.forces_only(ctypes.byref(self._step), reps)

    def run(self, n_sub: int, dt: float, thrust=None, damping: float = 0.0, gravity: float = 0.0,
            deform_damping: float = 0.0):
        """n_sub substeps; returns (max inverted elements seen, max squared speed).
        ``damping`` (1/s) acts on the absolute vertex velocities, ``deform_damping`` on their
        part relative to the body's rigid motion (reference.drift)."""
        f = self.fem
        self.thrust[:] = 0.0 if thrust is None else thrust
        if self._step is None:
            nb.set_num_threads(min(self.fbuf.shape[0], nb.config.NUMBA_NUM_THREADS))
            el, Bm, vol = self._elements
            return advance(self._kernels.linear_3d(self.real), n_sub, dt, self.x, self.v, self.q, self.fbuf, el,
                           Bm, vol, f.mu, f.lam, self.minv, self.mass, damping, deform_damping, gravity,
                           self.ground, self.boxes_min, self.boxes_max, self.friction, *self.rotors,
                           self.thrust, self.ext, self.dirs, self.fext, self.gravity_share, self.real)
        s = self._step
        now = tuple(a.__array_interface__["data"][0] for a in (self.x, self.v, self.q, self.fext))
        if (s.x, s.v, s.q, s.fext) != now:
            raise RuntimeError("Body state arrays were replaced or copied: assign into them (x[:] = ...)")
        s.n_sub, s.dt, s.damping, s.deform_damping, s.gravity = n_sub, dt, damping, deform_damping, gravity
        vmax2 = ctypes.c_double()
        worst = self._lib.advance(ctypes.byref(s), ctypes.byref(vmax2))
        if worst < 0:
            raise MemoryError("kernels.c advance: out of memory")
        return worst, vmax2.value
