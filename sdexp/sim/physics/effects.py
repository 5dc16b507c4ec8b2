"""Physical effects beyond the paper's simulator (which models rotor normal force only), and the
plugin protocol through which a user adds their own.

``sim.effects`` is a list of entries, each either ``{name: <library name>, <param>: value}`` or
``{_target_: package.module.Class, <param>: value}``. :func:`build_effects` turns the list into
objects; the :class:`Simulator` calls their hooks:

- ``modify_model(fem, damping, drone) -> (fem, damping)``: once, before the stable substep is
  computed (mass, stiffness, damping changes);
- ``setup(sim)``: once, after the model is final and ``sim.body`` exists (precompute vertex
  sets, areas);
- ``start(sim, rng)``: at the start of every flight (``sim.reset``), with a generator seeded by
  the simulator's seed and the flight's index: draw a random effect's realisation here (a gust
  sequence), so each flight differs, every run repeats, and a window re-initialisation inside
  the flight (``sim.set_state``) does not redraw it. ``rng`` is None when the simulator
  predicts (``Simulator(draws=False)``, the discrepancy windows): take the expectation;
- ``reset(sim)``: at every flight start and every re-initialisation (internal states such as
  motor speed);
- ``actuate(thrust, sim) -> thrust``: commanded -> applied thrust, once per control step, after
  the output delay FIFO and the rotor noise;
- ``body_forces(sim, f)``: add external forces (N) on the vertices into ``f`` (nv, dim), given
  the state at the start of the control step; held over its substeps;
- ``sense(readings, sim) -> readings``: the IMU readings, before the sensor noise.

Why body forces once per control step: every force here changes on the time scale of the
body's motion (drag time constants m/(c A |v|) of a second or more, a rotor's direction, the
wind), far slower than 10 ms; holding them over the substeps costs one array add per vertex in
the compiled loop, and keeps the no-effects path (a zero array) as fast as before.

A hook a class does not override is never called, so an effect pays only for what it does.
"""
from __future__ import annotations

import importlib
import inspect
import itertools
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from sdexp.errors import UserError
from sdexp.ranges import between, choices, nonnegative, positive


@dataclass
class FitSpec:
    """How the discrepancy workflow fits an effect (sdexp.discrepancy.candidates), declared by
    the effect itself: the same protocol for the library's effects and a user's ``_target_``.

    theta are the estimated parameters, with theta = 0 the nominal simulator (or ``base``);
    ``lower``/``upper`` are physical bounds (a drag never pushes, a bias stays within what a
    sensor can be off by): a fit that ends on one is reported and not accepted. The library
    parametrises so that the predictions move about linearly in theta (the fit linearises
    once); ``entry(theta, option)`` gives the effect's constructor arguments."""
    params: list                          # names of theta's entries
    steps: list                           # finite-difference steps: typical strengths
    lower: list
    upper: list
    entry: Callable                       # (theta, option) -> constructor kwargs
    report: Callable | None = None        # (theta, option) -> physical parameters; None = entry
    options: list = field(default_factory=lambda: [None])   # discrete choices fitted by enumeration
    base: Callable | None = None          # option -> kwargs at theta = 0 when that is not nominal
    anchor: list | None = None            # where the other columns are differenced
    scan: list | None = None              # theta values tried first (responses far from linear)
    memory: float = 0.0                   # s of past commands a prediction must replay (lags)
    check: Callable | None = None         # (theta, option) -> why the fit is not physical, or None


class Effect:
    """Base class of every effect; each hook is a no-op here.

    To be a discrepancy candidate, an effect declares what can be fitted: ``fit_params`` =
    {constructor argument: (lower, upper, typical step)} with physical bounds (theta is the
    value itself, 0 must mean "no effect"), or, for a re-parametrisation, a ``fit_spec``
    classmethod returning a :class:`FitSpec`.

    A library effect (``LIBRARY``) also declares what the bench and the tests need of it, so
    that it is one class: ``bench_strengths`` and ``zero``."""

    name = "effect"
    description = ""
    equation = ""
    fit_params: dict = {}
    # the discrepancy bench's hidden strengths (sdexp.discrepancy.bench): (constructor argument,
    # moderate, strong); a direction, a rotor or a point is drawn per scenario there
    bench_strengths: tuple | None = None
    # {constructor argument: its range (sdexp.ranges, as the config's fields declare theirs)},
    # checked by check_params in the constructor; what depends on the drone is checked in setup
    ranges: dict = {}

    def check_params(self, **values) -> None:
        """Each of ``values`` within the range its class declares for it."""
        for key, value in values.items():
            self.ranges[key]["range"].check(f"sim.effects: {self.name}.{key}", value)

    @classmethod
    def zero(cls, dim: int) -> dict | None:
        """Constructor arguments under which the effect does nothing on a ``dim``-D drone: the
        simulator runs bitwise as without it (tests/sim/test_effects.py). None: not declared, or
        not an effect of such a drone."""
        return None

    @classmethod
    def fit_spec(cls, drone) -> FitSpec | None:
        if not cls.fit_params:
            return None
        names = list(cls.fit_params)
        lo, hi, step = (list(v) for v in zip(*(cls.fit_params[n] for n in names)))
        return FitSpec(names, step, lo, hi, lambda th, o: {n: float(v) for n, v in zip(names, th)})

    def modify_model(self, fem, damping: float, drone):
        return fem, damping

    def setup(self, sim) -> None:
        pass

    def start(self, sim, rng: np.random.Generator) -> None:
        pass

    def reset(self, sim) -> None:
        pass

    def actuate(self, thrust: np.ndarray, sim) -> np.ndarray:
        return thrust

    def body_forces(self, sim, f: np.ndarray) -> None:
        pass

    def sense(self, readings, sim):
        return readings


def overrides(effect: Effect, hook: str) -> bool:
    return getattr(type(effect), hook) is not getattr(Effect, hook)


# ------------------------------------------------------------------------------ geometry helpers

def rotor_normals(x: np.ndarray, rotors) -> np.ndarray:
    """(m, dim) unit area-weighted normals of the rotor patches at positions x (the thrust
    directions of sdexp.sim.physics.reference.rotor_forces)."""
    f = rotors.faces
    if x.shape[1] == 3:
        u, w = x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]]
        # written out: np.cross costs ~100 us a call on these few faces
        n = np.stack([u[:, 1] * w[:, 2] - u[:, 2] * w[:, 1], u[:, 2] * w[:, 0] - u[:, 0] * w[:, 2],
                      u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]], axis=1)
    else:
        d = x[f[:, 1]] - x[f[:, 0]]
        n = np.stack([d[:, 1], -d[:, 0]], axis=1)
    out = np.add.reduceat(n, rotors.face_ptr[:-1], axis=0)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def patch_means(a: np.ndarray, rotors) -> np.ndarray:
    """(m, dim) mean of a per-vertex array over each rotor's bound vertices."""
    return np.add.reduceat(a[rotors.verts] * rotors.weights[:, None], rotors.vert_ptr[:-1], axis=0)


def vertex_areas(rest: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """Each vertex's share of one side of the surface (half the boundary area, or in 2D half
    the boundary length x 1 m depth): the area a thin plate shows to the air."""
    if boundary.shape[1] == 3:
        p0, p1, p2 = (rest[boundary[:, k]] for k in range(3))
        area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
    else:
        area = np.linalg.norm(rest[boundary[:, 1]] - rest[boundary[:, 0]], axis=1)
    a = np.zeros(len(rest))
    k = boundary.shape[1]
    np.add.at(a, boundary.ravel(), np.repeat(area / k, k))
    return 0.5 * a


def _vec(value, dim: int, key: str, name: str) -> np.ndarray:
    v = np.atleast_1d(np.asarray(value, dtype=float))
    if v.shape != (dim,):
        raise UserError(f"sim.effects: {name}.{key} = {np.asarray(value).tolist()} needs {dim} numbers")
    return v


def _horizontal(dim: int) -> list[int]:
    return [0, 2] if dim == 3 else [0]


def _axis_names(dim: int) -> list[str]:
    return ["x", "z"] if dim == 3 else ["x"]


def _inside(points: np.ndarray):
    """A test whether a horizontal point lies within the convex hull of ``points``."""
    if points.shape[1] == 1:
        lo, hi = points.min(), points.max()
        return lambda q: bool(lo <= q[0] <= hi)
    from scipy.spatial import Delaunay
    tri = Delaunay(points[np.unique(points.round(6), axis=0, return_index=True)[1]])
    return lambda q: bool(tri.find_simplex(np.asarray(q, dtype=float)) >= 0)


# ------------------------------------------------------------------------------ actuator effects

class MotorLag(Effect):
    name = "motor_lag"
    description = "Each rotor's thrust follows its command through a first-order lag (motor and propeller inertia)."
    equation = "tau dT/dt = T_cmd - T; applied = mean of T over the control step (exact for a held command)"

    fit_params = {"tau": (0.0, 0.3, 0.03)}   # s: slower than any multirotor motor and propeller
    bench_strengths = ("tau", 0.06, 0.12)
    ranges = {"tau": nonnegative("s")}

    @classmethod
    def zero(cls, dim):
        return {"tau": 0.0}

    @classmethod
    def fit_spec(cls, drone):
        spec = super().fit_spec(drone)
        spec.memory = 3 * cls.fit_params["tau"][1]   # a window replays 3 time constants of the slowest lag
        # a lag's response saturates with tau: linearised at 0 a strong one (0.12 s on the bench
        # leaf) was fitted 8% short, outside its interval; a scan picks where to linearise
        spec.scan = [[0.04], [0.08], [0.16]]
        return spec

    def __init__(self, tau: float = 0.05):
        self.check_params(tau=tau)
        self.tau = float(tau)

    def reset(self, sim) -> None:
        self.state = np.zeros(sim.drone.num_rotors)

    def actuate(self, thrust, sim):
        if not np.any(self.tau):   # tau may be one per rotor (a subclass's)
            return thrust
        h = sim.cfg.control_dt / self.tau
        decay = np.exp(-h)
        start = self.state
        self.state = thrust + (start - thrust) * decay
        return thrust + (start - thrust) * (1.0 - decay) / h


class ActuationDelay(Effect):
    name = "actuation_delay"
    description = "An extra transport delay between command and rotor (radio, ESC), fractional steps interpolated."
    equation = "T(t) = T_cmd(t - d), linear between control steps"

    fit_params = {"delay": (0.0, 0.3, 0.02)}
    bench_strengths = ("delay", 0.02, 0.05)
    ranges = {"delay": nonnegative("s")}

    @classmethod
    def zero(cls, dim):
        return {"delay": 0.0}

    @classmethod
    def fit_spec(cls, drone):
        spec = super().fit_spec(drone)
        # a delay shifts whole responses in time: no linearisation at 0 sees a long one
        spec.scan, spec.memory = [[0.03], [0.06], [0.12]], cls.fit_params["delay"][1]
        return spec

    def __init__(self, delay: float = 0.02):
        self.check_params(delay=delay)
        self.delay = float(delay)

    def reset(self, sim) -> None:
        steps = self.delay / sim.cfg.control_dt
        self.k = int(np.floor(steps))
        self.frac = steps - self.k
        zero = np.zeros(sim.drone.num_rotors)
        self.history = deque([zero] * (self.k + 2), maxlen=self.k + 2)

    def actuate(self, thrust, sim):
        if self.delay == 0.0:
            return thrust
        self.history.append(np.array(thrust, dtype=float))
        newer, older = self.history[-1 - self.k], self.history[-2 - self.k]
        return (1.0 - self.frac) * newer + self.frac * older


class ThrustLoss(Effect):
    name = "thrust_loss"
    description = "One rotor produces a fraction less thrust than commanded (worn or damaged propeller)."
    equation = "T_r = (1 - eta) T_cmd,r for the affected rotor r"
    bench_strengths = ("fraction", 0.15, 0.3)
    ranges = {"fraction": between(0, 1, "[)")}

    @classmethod
    def zero(cls, dim):
        return {"fraction": 0.0}

    @classmethod
    def fit_spec(cls, drone):
        # which rotor is a discrete choice, fitted by trying each
        return FitSpec(["fraction"], [0.1], [0.0], [0.9],
                       lambda th, o: {"rotor": int(o), "fraction": float(th[0])},
                       options=list(range(drone.num_rotors)))

    def __init__(self, rotor: int = 0, fraction: float = 0.2):
        self.check_params(fraction=fraction)
        self.rotor, self.fraction = int(rotor), float(fraction)

    def setup(self, sim) -> None:
        m = sim.drone.num_rotors
        if not 0 <= self.rotor < m:
            raise UserError(f"sim.effects: thrust_loss.rotor = {self.rotor} must be in [0, {m - 1}]")
        self.gain = np.ones(m)
        self.gain[self.rotor] = 1.0 - self.fraction

    def actuate(self, thrust, sim):
        return thrust * self.gain


class GroundEffect(Effect):
    name = "ground_effect"
    description = "A rotor close to the ground makes more thrust (Cheeseman-Bennett image-vortex model)."
    equation = "T = T_cmd / (1 - (R / 4h)^2), h = rotor height above the ground, clamped at h >= R/2"
    bench_strengths = ("radius", 1.0, 1.6)
    ranges = {"radius": nonnegative("m")}

    @classmethod
    def zero(cls, dim):
        return {"radius": 0.0}

    @classmethod
    def fit_spec(cls, drone):
        # theta = R^2: the thrust gain (R / 4h)^2 is linear in it; R up to 3 m, a drone's size
        return FitSpec(["radius_sq"], [1.0], [0.0], [9.0],
                       lambda th, o: {"radius": float(np.sqrt(max(th[0], 0.0)))})

    def __init__(self, radius: float = 0.5, ground: float = 0.0):
        self.check_params(radius=radius)
        self.radius, self.ground = float(radius), float(ground)

    def actuate(self, thrust, sim):
        if self.radius == 0.0:
            return thrust
        h = patch_means(sim.body.x, sim.drone.rotors)[:, 1] - self.ground
        h = np.maximum(h, 0.5 * self.radius)
        return thrust / (1.0 - (self.radius / (4.0 * h)) ** 2)


# ------------------------------------------------------------------------------ body effects

class RotorReactionTorque(Effect):
    name = "rotor_reaction_torque"
    description = ("Each spinning rotor turns the body the other way about its axis (3D only): a pure "
                   "torque on the whole body, or a couple on a motor-mount disc (mount_radius).")
    equation = ("tau_r = -s_r k T_r n_r (s_r = +-1 spin, alternating around the centre), as mass-weighted "
                "forces m_i a n_r x r_i about the centre of mass (or a couple on a mount disc)")
    bench_strengths = ("k", 0.15, 0.3)   # the sign (spin direction) drawn per scenario

    @classmethod
    def zero(cls, dim):
        return {"k": 0.0} if dim == 3 else None   # 3D only

    @classmethod
    def fit_spec(cls, drone):
        if drone.dim != 3:
            return None   # a 2D rotor axis lies in the plane
        # k's sign is the spin direction: both are physical
        return FitSpec(["k"], [0.02], [-0.5], [0.5], lambda th, o: {"k": float(th[0])})

    def __init__(self, k: float = 0.02, spin: Any = None, mount_radius: float | None = None):
        self.k = float(k)
        self.spin = None if spin is None else np.asarray(spin, dtype=float)
        self.mount_radius = mount_radius

    def setup(self, sim) -> None:
        d = sim.drone
        if d.dim != 3:
            raise UserError("sim.effects: rotor_reaction_torque needs a 3D drone (a 2D rotor axis lies in the plane)")
        # where the couple acts: with mount_radius, on the vertices within it of the rotor patch
        # (the motor mount plate), which twists a soft body locally; by default on the whole
        # body with mass-proportional weights about the centre of mass, i.e. its net effect,
        # a torque that turns the body without twisting it (a twist the sensors cannot see
        # would make the effect unidentifiable from re-initialised sensor states)
        r = d.rotors
        rest = sim.fem.rest
        self.mounts = []
        for i in range(r.count):
            v = r.verts[r.vert_ptr[i]:r.vert_ptr[i + 1]]
            if self.mount_radius is not None:
                c = rest[v].mean(axis=0)
                near = np.flatnonzero(np.linalg.norm(rest - c, axis=1) <= float(self.mount_radius))
                v = np.union1d(v, near)
            self.mounts.append(v)
        if self.spin is None:
            a = d.rotors.anchors - d.fem.rest.mean(axis=0)
            order = np.argsort(np.arctan2(a[:, 2], a[:, 0]))
            self.spin = np.empty(d.num_rotors)
            self.spin[order] = np.where(np.arange(d.num_rotors) % 2 == 0, 1.0, -1.0)
        elif self.spin.shape != (d.num_rotors,):
            raise UserError(f"sim.effects: rotor_reaction_torque.spin needs {d.num_rotors} entries")

    def body_forces(self, sim, f):
        if self.k == 0.0:
            return
        r = sim.drone.rotors
        x = sim.body.x
        n = rotor_normals(x, r)
        tau = -self.spin * self.k * sim.applied
        if self.mount_radius is None:
            m = sim.fem.mass
            off = x - m @ x / m.sum()
            for i in range(r.count):
                perp = off - np.outer(off @ n[i], n[i])
                # f_i = m_i a n x r_i: torque a sum m |r_perp|^2 n, zero net force
                a = tau[i] / max(m @ np.sum(perp * perp, axis=1), 1e-12)
                f += (a * m)[:, None] * np.cross(n[i], perp)
            return
        for i, v in enumerate(self.mounts):
            off = x[v] - x[v].mean(axis=0)
            off -= np.outer(off @ n[i], n[i])
            # sum_j off_j x (a n x off_j) = a sum |off_j|^2 n for offsets in the disc plane
            a = tau[i] / max(np.sum(off * off), 1e-12)
            f[v] += a * np.cross(n[i], off)


class RotorDrag(Effect):
    name = "rotor_drag"
    description = ("Blade flapping and induced drag: each rotor resists its in-plane velocity, linearly "
                   "(the standard multirotor drag model).")
    equation = "F_r = -k (v_r - (v_r . n_r) n_r), v_r the rotor patch velocity, spread over the patch"
    ranges = {"k": nonnegative("N s/m (drag resists motion)")}

    fit_params = {"k": (0.0, 5.0, 0.1)}   # N s/m; a drag never pushes
    bench_strengths = ("k", 0.6, 1.5)

    @classmethod
    def zero(cls, dim):
        return {"k": 0.0}

    def __init__(self, k: float = 0.1):
        self.check_params(k=k)
        self.k = float(k)

    def body_forces(self, sim, f):
        if self.k == 0.0:
            return
        r = sim.drone.rotors
        n = rotor_normals(sim.body.x, r)
        v = patch_means(sim.body.v, r)
        v_plane = v - np.sum(v * n, axis=1, keepdims=True) * n
        F = -self.k * v_plane
        np.add.at(f, r.verts, F[np.repeat(np.arange(r.count), np.diff(r.vert_ptr))] * r.weights[:, None])


class QuadraticDrag(Effect):
    name = "quadratic_drag"
    description = "Air drag on the surface, quadratic in the velocity relative to still air, per area-weighted vertex."
    equation = "f_i = -c a_i |v_i| v_i, c = rho C_d / 2 (N s^2/m^4), a_i the vertex's share of one side of the surface"
    ranges = {"c": nonnegative()}

    fit_params = {"c": (0.0, 2.0, 0.03)}  # rho C_d / 2 of a flat plate is ~0.7; never negative
    bench_strengths = ("c", 0.3, 0.7)

    @classmethod
    def zero(cls, dim):
        return {"c": 0.0}

    def __init__(self, c: float = 0.05):
        self.check_params(c=c)
        self.c = float(c)

    def setup(self, sim) -> None:
        self.area = vertex_areas(sim.fem.rest, sim.drone.boundary)[:, None]

    def air(self, sim) -> np.ndarray | float:
        return 0.0

    def body_forces(self, sim, f):
        if self.c == 0.0:
            return
        u = sim.body.v - self.air(sim)
        f -= self.c * self.area * np.linalg.norm(u, axis=1, keepdims=True) * u


# the wind fit's options: the axes its parameters lie along, the horizontal plane first
WIND_PLANES = {3: {"xz": (0, 2), "xy": (0, 1), "zy": (2, 1)}, 2: {"x": (0,), "y": (1,)}}


class Wind(QuadraticDrag):
    name = "wind"
    description = ("Moving air acting through the quadratic surface drag: a mean velocity, an optional "
                   "sinusoidal gust and optional random gusts (a first-order Gauss-Markov process, the "
                   "low-order form of the Dryden turbulence model, redrawn for every flight).")
    equation = ("f_i = -c a_i |v_i - w(t)| (v_i - w(t)), w(t) = w + g sin(2 pi f t) + n(t), "
                "dn = -n / T dt + s sqrt(2 / T) dW per axis (std s, correlation time T)")
    ranges = {**QuadraticDrag.ranges, "gust_std": nonnegative("m/s"), "gust_time": positive("s")}

    CHUNK = 1024   # gust samples drawn at a time: the sequence does not depend on how far a run looks
    bench_strengths = ("velocity", 1.5, 3.0)   # m/s, in a horizontal direction drawn per scenario

    @classmethod
    def zero(cls, dim):
        return {"velocity": [0.0] * dim, "c": 0.0}

    @classmethod
    def fit_spec(cls, drone):
        # theta = the dynamic-pressure vector |w| w of the mean wind (the drag is linear in it), up
        # to 5 m/s along each axis, in one plane of WIND_PLANES (the options, fitted in turn): the
        # horizontal one first, as before, or one through the up axis, where a rising or sinking
        # wind lies -- it lifts like a thrust change at hover but pushes with the climb rate. Two
        # parameters (2D: one) whatever the direction, so a horizontal wind fits exactly as it did.
        # theta = 0 is still air with the wind's drag
        dim, planes = drone.dim, WIND_PLANES[drone.dim]

        def entry(th, o):
            v, n = np.zeros(dim), np.linalg.norm(th)
            v[list(planes[o])] = th / np.sqrt(n) if n > 0 else 0.0
            return {"velocity": v.tolist()}
        k = len(planes[next(iter(planes))])
        return FitSpec(["q_a", "q_b"][:k], [1.0] * k, [-25.0] * k, [25.0] * k, entry,
                       report=lambda th, o: {**entry(th, o), "plane": o}, options=list(planes),
                       base=lambda o: {"velocity": [0.0] * dim})

    def __init__(self, velocity: Any = (1.0, 0.0, 0.0), c: float = 0.05, gust: Any = None,
                 gust_freq: float = 0.0, gust_std: float = 0.0, gust_time: float = 2.0):
        super().__init__(c)
        self.check_params(gust_std=gust_std, gust_time=gust_time)
        self.velocity = np.asarray(velocity, dtype=float)
        self.gust = None if gust is None else np.asarray(gust, dtype=float)
        self.gust_freq = float(gust_freq)
        self.gust_std, self.gust_time = float(gust_std), float(gust_time)
        self._noise = None

    def setup(self, sim) -> None:
        super().setup(sim)
        d = sim.drone.dim
        self.velocity = _vec(self.velocity, d, "velocity", self.name)
        self.gust = np.zeros(d) if self.gust is None else _vec(self.gust, d, "gust", self.name)
        self._dt = sim.cfg.control_dt

    def start(self, sim, rng) -> None:
        self._noise = None   # no generator: the gusts' expectation, none
        if self.gust_std > 0 and rng is not None:
            self._rng = rng
            self._noise = self.gust_std * rng.standard_normal((1, sim.drone.dim))   # stationary start

    def _random_gust(self, t: float) -> np.ndarray:
        k = max(int(round(t / self._dt)), 0)
        a = np.exp(-self._dt / self.gust_time)
        while k >= len(self._noise):   # exact discretisation of the process, a chunk at a time
            xi = self._rng.standard_normal((self.CHUNK, self._noise.shape[1]))
            seq = np.empty_like(xi)
            prev = self._noise[-1]
            for j in range(self.CHUNK):
                prev = a * prev + self.gust_std * np.sqrt(1 - a * a) * xi[j]
                seq[j] = prev
            self._noise = np.concatenate([self._noise, seq])
        return self._noise[k]

    def air(self, sim):
        w = self.velocity + self.gust * np.sin(2 * np.pi * self.gust_freq * sim.t)
        return w + self._random_gust(sim.t) if self._noise is not None else w


# ------------------------------------------------------------------------------ model effects

class Payload(Effect):
    name = "payload"
    description = "An extra point mass carried at an offset (battery, camera), lumped on the nearest vertices."
    equation = "m_i += m / n for the n vertices within radius of the rest point (at least the nearest)"
    bench_strengths = ("mass", 0.1, 0.25)   # kg, at a point drawn near the centre of mass
    ranges = {"mass": nonnegative("kg")}
    SCAN_MASS = 0.2   # kg: the fit's scan (fit_spec), between the bench's moderate and strong weights

    @classmethod
    def zero(cls, dim):
        return {"mass": 0.0}

    @classmethod
    def fit_spec(cls, drone):
        # theta = (mass, first moments mass x horizontal offset from the centre of mass): the
        # predictions are about linear in these; the point must lie over the body
        rest, m = drone.fem.rest, drone.fem.mass
        centre, horiz = m @ rest / m.sum(), _horizontal(drone.dim)
        over_body = _inside(rest[:, horiz])

        def point(th):
            q = centre.copy()
            if th[0] > 0:
                q[horiz] += np.asarray(th[1:]) / th[0]
            return q

        def check(th, o):
            q = point(th)
            return None if th[0] <= 0 or over_body(q[horiz]) else f"point {np.round(q, 2).tolist()} is not over the body"
        k = len(horiz)
        # where a heavy weight sits is far from linear in the moments (lumped on the vertices
        # near it, it also adds inertia): linearised at the centre alone, a strong payload off to
        # one side is fitted at a third of its moment and a thrust loss takes the rest (the
        # converged flower's bench, docs/discrepancy_workflow.md). So a scan first: a mass of
        # SCAN_MASS at the centre and half the body's horizontal radius of gyration out along each
        # diagonal (each axis in 2D); the fit linearises about the best of them
        offsets = rest[:, horiz] - centre[horiz]
        reach = 0.5 * float(np.sqrt(np.average((offsets ** 2).sum(1), weights=m)))
        dirs = [np.array(d, dtype=float) / np.sqrt(k) for d in itertools.product((-1.0, 1.0), repeat=k)]
        scan = [[cls.SCAN_MASS] + [0.0] * k] + [[cls.SCAN_MASS, *(cls.SCAN_MASS * reach * d)] for d in dirs]
        return FitSpec(["mass", *[f"mass_{a}" for a in _axis_names(drone.dim)]], [0.1] + [0.05] * k,
                       [0.0] + [-2.0] * k, [2.0] + [2.0] * k,
                       lambda th, o: {"mass": float(max(th[0], 0.0)), "point": point(th).tolist()},
                       anchor=[0.1] + [0.0] * k, check=check, scan=scan)

    def __init__(self, mass: float = 0.1, point: Any = None, radius: float = 0.3):
        self.check_params(mass=mass)
        self.mass, self.point, self.radius = float(mass), point, float(radius)

    def modify_model(self, fem, damping, drone):
        point = fem.rest.mean(axis=0) if self.point is None else _vec(self.point, fem.dim, "point", self.name)
        dist = np.linalg.norm(fem.rest - point, axis=1)
        verts = np.flatnonzero(dist <= self.radius)
        if len(verts) == 0:
            verts = np.array([np.argmin(dist)])
        mass = fem.mass.copy()
        mass[verts] += self.mass / len(verts)
        return replace(fem, mass=mass), damping


class StiffnessScale(Effect):
    name = "stiffness_scale"
    description = "The material is stiffer or softer than nominal (Young's modulus times a factor)."
    equation = "E = k E_nominal (both Lame parameters scale)"
    bench_strengths = ("scale", 0.6, 1.8)
    ranges = {"scale": positive()}

    @classmethod
    def zero(cls, dim):
        return {"scale": 1.0}

    @classmethod
    def fit_spec(cls, drone):
        # theta = the compliance change 1/scale - 1 (deflections are linear in it), scale 0.2-5;
        # strong changes move the bending frequencies, so a scan of 2^(j/4) finds where to linearise
        return FitSpec(["compliance"], [0.2], [-0.8], [4.0],
                       lambda th, o: {"scale": float(1.0 / (1.0 + th[0]))},
                       scan=[[2.0 ** -(j / 4) - 1.0] for j in (-4, -3, -2, -1, 1, 2, 3, 4)])

    def __init__(self, scale: float = 1.0):
        self.check_params(scale=scale)
        self.scale = float(scale)

    def modify_model(self, fem, damping, drone):
        return replace(fem, mu=fem.mu * self.scale, lam=fem.lam * self.scale), damping


class DampingScale(Effect):
    name = "damping_scale"
    description = "The material (and air) dissipates more or less than nominal: mass-proportional damping times a factor."
    equation = "c = k c_nominal in m_i dv_i/dt = f_i - c m_i v_i"
    bench_strengths = ("scale", 0.5, 2.0)
    ranges = {"scale": nonnegative()}

    @classmethod
    def zero(cls, dim):
        return {"scale": 1.0}

    @classmethod
    def fit_spec(cls, drone):
        return FitSpec(["excess"], [0.3], [-1.0], [9.0], lambda th, o: {"scale": float(max(1.0 + th[0], 0.0))})

    def __init__(self, scale: float = 1.0):
        self.check_params(scale=scale)
        self.scale = float(scale)

    def modify_model(self, fem, damping, drone):
        return fem, damping * self.scale


# ------------------------------------------------------------------------------ sensor effects

class ImuBias(Effect):
    name = "imu_bias"
    description = ("A constant offset on one reading of the IMUs: attitude (an accelerometer bias tilts "
                   "the gravity reference), gyro rate, position or velocity.")
    equation = "rot' = exp([b]x) rot (2D: theta + b); omega' = omega + b; pos' = pos + b; vel' = vel + b"

    CHANNELS = ("rot", "omega", "pos", "vel")
    ranges = {"channel": choices(CHANNELS)}
    bench_strengths = ("value", 0.02, 0.05)   # rad: an attitude tilt in a direction drawn per scenario

    @classmethod
    def zero(cls, dim):
        return {"channel": "rot", "value": [0.0] * (3 if dim == 3 else 1)}

    @classmethod
    def fit_spec(cls, drone):
        # a tilt of the attitude reference; an accelerometer offset b tilts it by b / g, and
        # +-0.1 rad (+-1 m/s^2) is beyond an uncalibrated consumer MEMS part's zero-g offset
        three = drone.dim == 3
        value = (lambda th: [float(th[0]), 0.0, float(th[1])]) if three else (lambda th: [float(th[0])])
        k = 2 if three else 1
        return FitSpec(["tilt_x", "tilt_z"] if three else ["tilt"], [0.01] * k, [-0.1] * k, [0.1] * k,
                       lambda th, o: {"channel": "rot", "value": value(th)})

    def __init__(self, channel: str = "rot", value: Any = (0.02, 0.0, 0.0), imus: Any = None):
        self.check_params(channel=channel)
        self.channel, self.imus = channel, imus
        self.value = np.asarray(value, dtype=float)

    def setup(self, sim) -> None:
        d = sim.drone.dim
        n = (3 if d == 3 else 1) if self.channel in ("rot", "omega") else d
        self.value = _vec(self.value, n, "value", self.name)
        k = sim.drone.imus.idx.shape[0]
        self.idx = np.arange(k) if self.imus is None else np.asarray(self.imus, dtype=int)
        if self.idx.size and (self.idx.min() < 0 or self.idx.max() >= k):
            raise UserError(f"sim.effects: imu_bias.imus must index the drone's {k} IMUs")
        if self.channel == "rot" and d == 3:
            from sdexp.sensing.rotations import exp_so3
            self.rot = exp_so3(self.value)

    def sense(self, r, sim):
        if not np.any(self.value):
            return r
        i = self.idx
        if self.channel == "pos":
            pos = r.pos.copy(); pos[i] += self.value
            return replace(r, pos=pos)
        if self.channel == "vel":
            vel = r.vel.copy(); vel[i] += self.value
            return replace(r, vel=vel)
        if self.channel == "omega":
            om = np.array(r.omega, dtype=float); om[i] += self.value if om.ndim == 2 else self.value[0]
            return replace(r, omega=om)
        rot = np.array(r.rot, dtype=float)
        rot[i] = self.rot @ rot[i] if rot.ndim == 3 else rot[i] + self.value[0]
        return replace(r, rot=rot)


LIBRARY: dict[str, type[Effect]] = {c.name: c for c in (
    RotorReactionTorque, RotorDrag, QuadraticDrag, GroundEffect, MotorLag, ActuationDelay, Wind,
    ThrustLoss, Payload, StiffnessScale, DampingScale, ImuBias)}


def _import(path: str, where: str):
    module, _, attr = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError, ValueError) as err:
        raise UserError(f"{where}: _target_ {path!r} cannot be imported: {err}") from None


def resolve_effect(entry, where: str) -> tuple[type, dict, dict]:
    """(class, constructor arguments, head) of an entry: a library name, ``{name: ..., args}``
    or ``{_target_: package.module.Class, args}``; head is the entry's identifying key."""
    e = {"name": entry} if isinstance(entry, str) else dict(entry)
    if "_target_" in e:
        path = e.pop("_target_")
        e.pop("name", None)
        return _import(path, where), e, {"_target_": path}
    name = e.pop("name", None)
    if name not in LIBRARY:
        field_ = f"{where}.name" if where.startswith("sim.effects") else where
        raise UserError(f"{field_} = {name!r} is unknown: choose one of {sorted(LIBRARY)} or give a _target_ class")
    return LIBRARY[name], e, {"name": name}


def check_config_effects(entries) -> None:
    """sim.effects as a user wrote them (plain dicts): known names, known parameters, physical ranges."""
    build_effects([dict(e) if isinstance(e, dict) else e for e in entries or []])


def build_effects(entries) -> list[Effect]:
    """Objects from ``sim.effects`` entries (dicts or Effect instances)."""
    out = []
    for k, e in enumerate(entries or []):
        if isinstance(e, Effect):
            out.append(e)
            continue
        if not isinstance(e, dict):
            raise UserError(f"sim.effects[{k}] = {e!r}: expected {{name: ..., params}} or {{_target_: ...}}")
        cls, e, _ = resolve_effect(e, f"sim.effects[{k}]")
        label = getattr(cls, "name", getattr(cls, "__name__", str(cls)))
        try:
            allowed = [q for q in inspect.signature(cls).parameters if q not in ("self", "args", "kwargs")]
        except (TypeError, ValueError):
            allowed = None
        unknown = [q for q in e if allowed is not None and q not in allowed]
        if unknown:
            raise UserError(f"sim.effects[{k}].{unknown[0]} is not a parameter of {label}: allowed "
                            f"{', '.join(allowed) or 'none'}")
        try:
            obj = cls(**e)
        except UserError as err:   # a value out of the effect's physical range
            raise UserError(f"sim.effects[{k}] ({label}): {str(err).removeprefix('sim.effects: ')}") from None
        except TypeError as err:
            raise UserError(f"sim.effects[{k}] ({label}): {err}; allowed parameters "
                            f"{', '.join(allowed or [])}") from None
        if not isinstance(obj, Effect):
            raise UserError(f"sim.effects[{k}]: {cls} is not an sdexp.sim.physics.effects.Effect")
        out.append(obj)
    return out
