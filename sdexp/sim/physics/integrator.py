"""The explicit substep: elastic forces, rotor thrust, gravity, mass-proportional damping (of the
vertex velocities and of their deformation part), symplectic Euler, contact with the ground and
static boxes. ``Body`` holds the state arrays and runs whole control steps in compiled code
(kernels.c's ``advance``); the numba functions here are its reference and fallback.
"""
from __future__ import annotations

import ctypes

import numba as nb
import numpy as np

from sdexp.sim.physics.fem import PRECISIONS, FemModel, element_data, element_forces, kernels, rest_quaternions
from sdexp.sim.physics.native import Step, blocked


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def rotor_forces(x, tri_ptr, tris, vert_ptr, verts, weights, thrust, ext, dirs):
    """Thrust of rotor r acts along the area-weighted normal of its bound surface triangles
    (3D) or segments (2D), spread over its bound vertices by ``weights``.
    Writes the unit directions into dirs (m, dim) and the forces into ext (patch rows only)."""
    dim = x.shape[1]
    m = thrust.shape[0]
    for r in range(m):
        for k in range(vert_ptr[r], vert_ptr[r + 1]):
            for c in range(dim):
                ext[verts[k], c] = 0.0
    for r in range(m):
        nx = 0.0; ny = 0.0; nz = 0.0
        for k in range(tri_ptr[r], tri_ptr[r + 1]):
            a = tris[k, 0]; b = tris[k, 1]
            if dim == 3:
                c = tris[k, 2]
                ux = x[b, 0] - x[a, 0]; uy = x[b, 1] - x[a, 1]; uz = x[b, 2] - x[a, 2]
                wx = x[c, 0] - x[a, 0]; wy = x[c, 1] - x[a, 1]; wz = x[c, 2] - x[a, 2]
                nx += uy * wz - uz * wy; ny += uz * wx - ux * wz; nz += ux * wy - uy * wx
            else:
                # outward normal of a counter-clockwise boundary segment a->b
                nx += x[b, 1] - x[a, 1]; ny -= x[b, 0] - x[a, 0]
        inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz + 1e-300)
        nx *= inv; ny *= inv; nz *= inv
        dirs[r, 0] = nx; dirs[r, 1] = ny
        if dim == 3:
            dirs[r, 2] = nz
        for k in range(vert_ptr[r], vert_ptr[r + 1]):
            i = verts[k]
            f = thrust[r] * weights[k]
            ext[i, 0] += f * nx; ext[i, 1] += f * ny
            if dim == 3:
                ext[i, 2] += f * nz


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


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def damp_deformation(x, v, mass, minv, keep):
    """Implicit mass-proportional damping of the deformation velocity: every free vertex keeps
    ``keep`` of its velocity relative to the body's rigid motion (centre-of-mass velocity plus
    the angular velocity that carries the angular momentum). Frame-indifferent, as the paper's
    Eq. 3 needs: it removes no linear or angular momentum, so a spinning or drifting body is not
    slowed, only its vibrations are."""
    nv, dim = x.shape
    M = 0.0
    c = np.zeros(3); p = np.zeros(3); L = np.zeros(3); S = np.zeros((3, 3))
    for i in range(nv):
        if minv[i] == 0.0:
            continue
        m = mass[i]
        M += m
        for a in range(dim):
            c[a] += m * x[i, a]; p[a] += m * v[i, a]
    c /= M; p /= M
    for i in range(nv):
        if minv[i] == 0.0:
            continue
        m = mass[i]
        r0 = x[i, 0] - c[0]; r1 = x[i, 1] - c[1]; u0 = v[i, 0] - p[0]; u1 = v[i, 1] - p[1]
        r2 = 0.0; u2 = 0.0
        if dim == 3:
            r2 = x[i, 2] - c[2]; u2 = v[i, 2] - p[2]
        L[0] += m * (r1 * u2 - r2 * u1)
        L[1] += m * (r2 * u0 - r0 * u2)
        L[2] += m * (r0 * u1 - r1 * u0)
        S[0, 0] += m * r0 * r0; S[0, 1] += m * r0 * r1; S[0, 2] += m * r0 * r2
        S[1, 1] += m * r1 * r1; S[1, 2] += m * r1 * r2; S[2, 2] += m * r2 * r2
    S[1, 0] = S[0, 1]; S[2, 0] = S[0, 2]; S[2, 1] = S[1, 2]
    w = np.zeros(3)
    if dim == 3:
        inertia = (S[0, 0] + S[1, 1] + S[2, 2]) * np.eye(3) - S
        w = np.linalg.solve(inertia, L)
    else:
        w[2] = L[2] / (S[0, 0] + S[1, 1])
    for i in range(nv):
        if minv[i] == 0.0:
            continue
        r0 = x[i, 0] - c[0]; r1 = x[i, 1] - c[1]; r2 = x[i, 2] - c[2] if dim == 3 else 0.0
        rig0 = p[0] + w[1] * r2 - w[2] * r1
        rig1 = p[1] + w[2] * r0 - w[0] * r2
        v[i, 0] = rig0 + keep * (v[i, 0] - rig0)
        v[i, 1] = rig1 + keep * (v[i, 1] - rig1)
        if dim == 3:
            rig2 = p[2] + w[0] * r1 - w[1] * r0
            v[i, 2] = rig2 + keep * (v[i, 2] - rig2)


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def integrate(x, v, fbuf, minv, mass, ext, fext, dt, damping, deform_damping, gravity, ground, boxes_min, boxes_max,
              friction, gravity_share):
    """Symplectic Euler with implicit mass-proportional damping, then contact projection.
    ``fext`` (nv, dim): external forces other than thrust (effects' body hooks), held over
    the control step; zeros when no effect pushes on the body. ``mass``, ``minv``: the inertial
    mass; ``gravity_share`` (nv,): physical over inertial mass (sim.mass_scaling; gravity pulls
    on the physical mass).
    ``ground`` is -inf when there is no ground; minv = 0 pins a vertex. Serial: per vertex it
    is a few dozen flops, less than the cost of a parallel region on meshes this size.
    Returns the largest squared speed."""
    nv, dim = x.shape
    nt = fbuf.shape[0]
    nb_box = boxes_min.shape[0]
    vmax2 = 0.0
    scale = 1.0 / (1.0 + dt * damping)
    for i in range(nv):
        fx = ext[i, 0] + fext[i, 0]; fy = ext[i, 1] + fext[i, 1]; fz = 0.0
        if dim == 3:
            fz = ext[i, 2] + fext[i, 2]
        for t in range(nt):
            fx += fbuf[t, i, 0]; fy += fbuf[t, i, 1]
            if dim == 3:
                fz += fbuf[t, i, 2]
        mi = minv[i]
        g = gravity * gravity_share[i] if mi > 0.0 else 0.0
        v[i, 0] = (v[i, 0] + dt * fx * mi) * scale
        v[i, 1] = (v[i, 1] + dt * (fy * mi - g)) * scale
        if dim == 3:
            v[i, 2] = (v[i, 2] + dt * fz * mi) * scale
    if deform_damping > 0.0:
        damp_deformation(x, v, mass, minv, 1.0 / (1.0 + dt * deform_damping))
    for i in range(nv):
        vx = v[i, 0]; vy = v[i, 1]; vz = 0.0
        if dim == 3:
            vz = v[i, 2]
        px = x[i, 0] + dt * vx; py = x[i, 1] + dt * vy; pz = 0.0
        if dim == 3:
            pz = x[i, 2] + dt * vz
        # contact: project out along the normal, cancel the inward normal velocity and take
        # Coulomb friction off the tangential velocity
        if py < ground:
            py = ground
            if vy < 0.0:
                vt = np.sqrt(vx * vx + vz * vz)
                keep = max(0.0, 1.0 - friction * (-vy) / (vt + 1e-12))
                vx *= keep; vz *= keep; vy = 0.0
        for b in range(nb_box):
            inside = px > boxes_min[b, 0] and px < boxes_max[b, 0] and \
                py > boxes_min[b, 1] and py < boxes_max[b, 1]
            if dim == 3:
                inside = inside and pz > boxes_min[b, 2] and pz < boxes_max[b, 2]
            if inside:
                best = 1e300; axis = 0; side = 0.0
                for c in range(dim):
                    p = px if c == 0 else (py if c == 1 else pz)
                    lo = p - boxes_min[b, c]; hi = boxes_max[b, c] - p
                    if lo < best:
                        best = lo; axis = c; side = -1.0
                    if hi < best:
                        best = hi; axis = c; side = 1.0
                vn = vx if axis == 0 else (vy if axis == 1 else vz)
                if axis == 0:
                    px += side * best
                elif axis == 1:
                    py += side * best
                else:
                    pz += side * best
                if vn * side < 0.0:
                    t2 = vx * vx + vy * vy + vz * vz - vn * vn
                    keep = max(0.0, 1.0 - friction * abs(vn) / (np.sqrt(max(t2, 0.0)) + 1e-12))
                    vx *= keep; vy *= keep; vz *= keep
                    if axis == 0:
                        vx = 0.0
                    elif axis == 1:
                        vy = 0.0
                    else:
                        vz = 0.0
        x[i, 0] = px; x[i, 1] = py
        v[i, 0] = vx; v[i, 1] = vy
        if dim == 3:
            x[i, 2] = pz; v[i, 2] = vz
        vmax2 = max(vmax2, vx * vx + vy * vy + vz * vz)
    return vmax2


@nb.njit(cache=True)
def advance(kernel, n_sub, dt, x, v, q, fbuf, elems, Bm, vol, mu, lam, minv, mass, damping,
            deform_damping, gravity, ground, boxes_min, boxes_max, friction, tri_ptr, tris, vert_ptr, verts,
            weights, thrust, ext, dirs, fext, gravity_share, real):
    """Run n_sub substeps; one force buffer per thread in fbuf (nt, nv, dim). ``kernel``: the
    C-signature 3D force kernel (sdexp.sim.physics.native) in ``real``, the force arithmetic.
    Returns (max inverted elements seen, max squared speed)."""
    worst = 0
    vmax2 = 0.0
    dim = x.shape[1]
    for _ in range(n_sub):
        worst = max(worst, element_forces(kernel, x, elems, Bm, vol, mu, lam, q, fbuf, real))
        rotor_forces(x, tri_ptr, tris, vert_ptr, verts, weights, thrust, ext, dirs)
        vmax2 = max(vmax2, integrate(x, v, fbuf, minv, mass, ext, fext, dt, damping, deform_damping, gravity, ground,
                                     boxes_min, boxes_max, friction, gravity_share))
    return worst, vmax2


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
        part relative to the body's rigid motion (``damp_deformation``)."""
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
