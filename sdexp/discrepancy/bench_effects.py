"""Effects outside the library, for the discrepancy bench: written as a user would, through the
plugin protocol (``_target_`` entries), with other equations than the library's.

Two kinds. ``VARIANTS`` have a fair library answer (a per-rotor spread of lags is answered well by
one mean lag, a swinging hanging weight by a rigid payload): the bench scores whether that answer
is named. ``UNMODELLED`` have none: the honest answer is ``unexplained`` (or, where part of the gap
is a library effect's, that effect with the rest reported above the floor).

Each declares its parameters' physical ranges (``ranges``, checked by its constructor as the
library's effects do theirs): a value out of range is an error naming the key and the range.
"""
from __future__ import annotations

import numpy as np

from sdexp.errors import UserError
from sdexp.ranges import between, nonnegative, positive, ranged
from sdexp.sim.physics.effects import Effect, MotorLag, rotor_normals, vertex_areas


class RotorTilt(Effect):
    """Rotor ``rotor`` is mounted tilted by ``angle`` about its patch's local horizontal, so part
    of its thrust pushes sideways."""
    name = "rotor_tilt"
    fit_params = {"angle": (-0.5, 0.5, 0.05)}   # rad: what a user declares to make it a candidate
    ranges = {"angle": between(-1.5, 1.5, unit="rad (a mount tilted 90 deg lifts nothing)"), "rotor": nonnegative()}

    def __init__(self, angle: float = 0.15, rotor: int = 0):
        self.check_params(angle=angle, rotor=rotor)
        self.angle, self.rotor = float(angle), int(rotor)

    def setup(self, sim):
        m = sim.drone.num_rotors
        if self.rotor >= m:
            raise UserError(f"sim.effects: rotor_tilt.rotor = {self.rotor} is out of range: allowed 0 to {m - 1}")

    def body_forces(self, sim, f):
        r = sim.drone.rotors
        n = rotor_normals(sim.body.x, r)[self.rotor]
        side = np.zeros_like(n)
        side[0] = 1.0
        side -= (side @ n) * n
        side /= np.linalg.norm(side)
        i0, i1 = r.vert_ptr[self.rotor], r.vert_ptr[self.rotor + 1]
        F = sim.applied[self.rotor] * np.sin(self.angle) * side
        f[r.verts[i0:i1]] += F * r.weights[i0:i1, None]


class PerRotorLag(MotorLag):
    """Each rotor follows its command through its own first-order lag (motors that differ)."""
    name = "per_rotor_lag"
    ranges = {**MotorLag.ranges, "taus": nonnegative("s")}

    def __init__(self, taus=(0.05, 0.1)):
        if not len(taus):
            raise UserError("sim.effects: per_rotor_lag.taus = [] is out of range: allowed one or more >= 0 s")
        self.check_params(taus=list(taus))
        super().__init__(float(np.min(taus)))
        self.taus = np.asarray(taus, dtype=float)

    def setup(self, sim):
        self.tau = np.resize(self.taus, sim.drone.num_rotors)   # MotorLag's step, one tau a rotor


class HangingMass(Effect):
    """A weight hung on an elastic line below the body's centre: it swings, and pulls on the
    vertices it hangs from (a spring-damper to the attachment point, integrated each step)."""
    name = "hanging_mass"
    ranges = {"mass": positive("kg"), "length": nonnegative("m"), "stiffness": positive("N/m"),
              "damping": nonnegative("N s/m"), "radius": nonnegative("m")}

    def __init__(self, mass: float = 0.2, length: float = 0.5, stiffness: float = 20.0, damping: float = 0.5,
                 radius: float = 0.3):
        self.check_params(mass=mass, length=length, stiffness=stiffness, damping=damping, radius=radius)
        self.mass, self.length, self.k, self.c, self.radius = mass, length, stiffness, damping, radius

    def setup(self, sim):
        rest = sim.fem.rest
        centre = sim.fem.mass @ rest / sim.fem.mass.sum()
        d = np.linalg.norm(rest - centre, axis=1)
        self.verts = np.flatnonzero(d <= self.radius)
        if len(self.verts) == 0:
            self.verts = np.array([np.argmin(d)])
        self.down = np.zeros(sim.drone.dim)
        self.down[1] = -1.0

    def reset(self, sim):
        # the weight at rest under the attachment, the line stretched by its weight
        a = sim.body.x[self.verts].mean(axis=0)
        g = sim.cfg.gravity
        self.pos = a + self.down * (self.length + self.mass * g / self.k)
        self.vel = sim.body.v[self.verts].mean(axis=0)

    def _pull(self, a, va):
        d = self.pos - a
        n = np.linalg.norm(d)
        u = d / max(n, 1e-9)
        stretch = max(n - self.length, 0.0)   # a line pulls, never pushes
        return (self.k * stretch + self.c * max((self.vel - va) @ u, 0.0) * (stretch > 0)) * u

    def body_forces(self, sim, f):
        a = sim.body.x[self.verts].mean(axis=0)
        va = sim.body.v[self.verts].mean(axis=0)
        steps, dt = 10, sim.cfg.control_dt / 10
        pull = np.zeros_like(a)
        for _ in range(steps):   # the weight's own motion, semi-implicit, over the control step
            p = self._pull(a, va)
            self.vel = self.vel + dt * (-p / self.mass + self.down * sim.cfg.gravity)
            self.pos = self.pos + dt * self.vel
            pull += p / steps
        f[self.verts] += pull / len(self.verts)


class ThrustCurve(Effect):
    """The rotors make less thrust than commanded at high commands (a propeller's thrust curve
    flattening, voltage drop under load): T = T_cmd (1 - a |T_cmd| / T_max)."""
    name = "thrust_curve"
    ranges = {"a": between(0, 1)}   # 1: no thrust left at a full command; more would pull

    def __init__(self, a: float = 0.3):
        self.check_params(a=a)
        self.a = float(a)

    def actuate(self, thrust, sim):
        return thrust * (1.0 - self.a * np.abs(thrust) / sim.drone.max_thrust)


class BatterySag(Effect):
    """The battery's voltage falls over the flight, and every rotor's thrust with it."""
    name = "battery_sag"
    ranges = {"rate": nonnegative("1/s")}

    def __init__(self, rate: float = 0.02):
        self.check_params(rate=rate)
        self.rate = float(rate)   # fraction of thrust lost per second of flight

    def actuate(self, thrust, sim):
        return thrust * max(1.0 - self.rate * sim.t, 0.0)


class Updraft(Effect):
    """Air rising through the body (thermal, rotor wash off a wall): quadratic drag against a
    vertical air velocity, written as a user would; its fair library answer is a vertical wind."""
    name = "updraft"
    ranges = {"speed": ranged(lambda v: True, "finite m/s (< 0: a downdraft)"), "c": nonnegative()}

    def __init__(self, speed: float = 2.0, c: float = 0.05):
        self.check_params(speed=speed, c=c)
        self.speed, self.c = float(speed), float(c)

    def setup(self, sim):
        self.area = vertex_areas(sim.fem.rest, sim.drone.boundary)[:, None]
        self.air = np.zeros(sim.drone.dim)
        self.air[1] = self.speed

    def body_forces(self, sim, f):
        u = sim.body.v - self.air
        f -= self.c * self.area * np.linalg.norm(u, axis=1, keepdims=True) * u


class OneSidedDrag(Effect):
    """Air drag on one side of the body only (a camera or a flag on the +x half): the drag pulls
    off the centre and turns the body as it flies."""
    name = "one_sided_drag"
    ranges = {"c": nonnegative()}   # a drag never pushes

    def __init__(self, c: float = 0.6):
        self.check_params(c=c)
        self.c = float(c)

    def setup(self, sim):
        rest = sim.fem.rest
        area = vertex_areas(rest, sim.drone.boundary)
        self.area = (area * (rest[:, 0] > rest[:, 0].mean()))[:, None]

    def body_forces(self, sim, f):
        v = sim.body.v
        f -= self.c * self.area * np.linalg.norm(v, axis=1, keepdims=True) * v


class Crosstalk(Effect):
    """Each rotor's command leaks into the next rotor's (shared ESC wiring): T = (1 - e) T_cmd,r +
    e T_cmd,r+1."""
    name = "crosstalk"
    ranges = {"leak": between(0, 1)}

    def __init__(self, leak: float = 0.2):
        self.check_params(leak=leak)
        self.leak = float(leak)

    def actuate(self, thrust, sim):
        return (1.0 - self.leak) * thrust + self.leak * np.roll(thrust, -1)


PATH = "sdexp.discrepancy.bench_effects."


def variants(drone, rng) -> list[tuple[str, str, dict]]:
    """(id, fair library answer, effect entry) of the outside-the-library effects that have one."""
    m = drone.num_rotors
    d = rng.normal(size=2 if drone.dim == 3 else 1)
    d /= np.linalg.norm(d)
    horiz = np.zeros(drone.dim)
    horiz[[0, 2] if drone.dim == 3 else [0]] = d

    up = np.zeros(drone.dim)
    up[1] = 1.0

    def gusty(mean, std, direction=horiz):
        return {"name": "wind", "velocity": (mean * direction).tolist(), "gust_std": std, "gust_time": 1.5}
    return [
        ("gusty_wind-a", "wind", gusty(1.5, 0.75)),
        ("gusty_wind-b", "wind", gusty(3.0, 1.5)),
        ("per_rotor_lag", "motor_lag", {"_target_": PATH + "PerRotorLag",
                                        "taus": rng.uniform(0.06, 0.16, m).round(3).tolist()}),
        ("hanging_mass", "payload", {"_target_": PATH + "HangingMass", "mass": 0.3}),
        ("gusty_updraft", "wind", gusty(3.0, 1.4, up)),   # the case: 3 m/s up, gusts 1.4 m/s
        ("updraft", "wind", {"_target_": PATH + "Updraft", "speed": 2.0}),
    ]


def unmodelled(drone, rng) -> list[tuple[str, dict]]:
    """(id, effect entry) of the outside-the-library effects without a library answer."""
    return [
        ("rotor_tilt", {"_target_": PATH + "RotorTilt", "angle": 0.15, "rotor": int(rng.integers(drone.num_rotors))}),
        ("thrust_curve", {"_target_": PATH + "ThrustCurve", "a": 0.3}),
        ("battery_sag", {"_target_": PATH + "BatterySag", "rate": 0.02}),
        ("one_sided_drag", {"_target_": PATH + "OneSidedDrag", "c": 0.6}),
        ("crosstalk", {"_target_": PATH + "Crosstalk", "leak": 0.2}),
    ]
