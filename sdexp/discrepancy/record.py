"""``sdexp experiment=record``: fly the simulator through manoeuvres chosen to excite every
library effect, and write the flights in the log format (sdexp.discrepancy.logs).

A small rigid-body PD pilot (position -> tilt -> torques -> rotor mixer, on the noisy sensor
state only) keeps the drone in the air while each manoeuvre adds its excitation:

- ``hover``: hold the setpoint (the null regime);
- ``steps``: setpoint jumps, so the thrust steps (motor lag, actuation delay);
- ``random_holds``: random per-rotor thrust offsets held 0.3 s (thrust loss, payload, stiffness);
- ``ground_pass``: descend to skim the ground and climb back (ground effect);
- ``differential``: a thrust pattern along the rotors' spin signs, zero net force and torque
  on a rigid body (rotor reaction torque yaws the drone, bending changes);
- ``high_speed``: a fast horizontal leg and a stop (drag, wind, rotor drag).

The pilot lives here, not in sdexp.control: it only has to keep a log-recording flight in the
air, with gains low enough for a soft body, and needs no learned model.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sdexp.discrepancy.logs import meta_for, state_row, write_flight, write_meta
from sdexp.errors import UserError

log = logging.getLogger(__name__)


MANOEUVRES = ("hover", "steps", "random_holds", "ground_pass", "differential", "high_speed")


def spin_signs(drone) -> np.ndarray:
    """+-1 alternating around the centre: the default spin of rotor_reaction_torque."""
    a = drone.rotors.anchors - drone.fem.rest.mean(axis=0)
    ang = np.arctan2(a[:, 2], a[:, 0]) if drone.dim == 3 else a[:, 0]
    sign = np.empty(drone.num_rotors)
    sign[np.argsort(ang)] = np.where(np.arange(drone.num_rotors) % 2 == 0, 1.0, -1.0)
    return sign


class Pilot:
    """PD position and attitude control of the drone taken as rigid, through a least-norm
    mixer from (total thrust, body torques) to rotor thrusts."""

    def __init__(self, drone, gravity: float, att_freq: float = 2.5, pos_freq: float = 0.7,
                 max_tilt: float = 0.3, dt: float = 0.01):
        self.dim = drone.dim
        from sdexp.sim.physics.effects import patch_means
        rest = drone.fem.rest
        m = drone.fem.mass
        c = m @ rest / m.sum()   # the centre of mass, not the vertex mean
        self.mass, self.g, self.max_tilt = m.sum(), gravity, max_tilt
        # where the thrust acts: the patches' vertex means, not the nominal anchors
        a = patch_means(rest, drone.rotors) - c
        if self.dim == 3:
            # total thrust, torque about body x (-z T), about body z (+x T)
            mix = np.stack([np.ones(len(a)), -a[:, 2], a[:, 0]])
            self.inertia = np.array([m @ (rest[:, 2] - c[2]) ** 2, m @ (rest[:, 0] - c[0]) ** 2])
        else:
            mix = np.stack([np.ones(len(a)), a[:, 0]])
            self.inertia = np.array([m @ (rest[:, 0] - c[0]) ** 2])
        self.unmix = np.linalg.pinv(mix)
        # wing-tilt map: a peripheral IMU at rest direction r raised by s turns its wing about
        # r x Y; averaging that into the attitude makes the feedback see the rotors' own tilt
        # (collocated), which keeps the wings' bending modes from being driven unstable
        r = drone.layout.r_hat
        if self.dim == 3:
            axes = np.c_[-r[:, 2], r[:, 0]]                 # (n_s, 2): effect on (e_x, e_z)
        else:
            axes = np.sign(r[:, :1])
        norm = np.sum(axes ** 2, axis=0)
        self.wing = np.divide(axes, norm, out=np.zeros_like(axes), where=norm > 0)
        self.kp_a, self.kd_a = att_freq ** 2, 2 * 0.8 * att_freq
        self.kp_p, self.kd_p = pos_freq ** 2, 2 * 0.9 * pos_freq
        self.max_thrust = drone.max_thrust
        self.ki, self.dt, self.integral = 0.5 * pos_freq ** 3, dt, 0.0

    def reset(self) -> None:
        self.integral = 0.0

    def act(self, st, target, target_vel) -> np.ndarray:
        acc = self.kp_p * (target - st.p) + self.kd_p * (target_vel - st.p_dot)
        # integral on height only: the bent wings' tilted thrust makes a steady sag
        self.integral = np.clip(self.integral + self.dt * (target[1] - st.p[1]), -2.0, 2.0)
        acc[1] += self.ki * self.integral
        if self.dim == 3:
            ex, ey, ez = st.e
            c, s = np.cos(ey), np.sin(ey)
            # small-angle thrust direction Ry(ey) (-ez, 1, ex): solve for the tilt giving acc
            ax, az = acc[0] / self.g, acc[2] / self.g
            want = np.clip([ax * s + az * c, -(ax * c - az * s)], -self.max_tilt, self.max_tilt)
            err = want - (np.array([ex, ez]) + st.s @ self.wing)
            rate = st.e_dot[[0, 2]] + st.s_dot @ self.wing
            torque = self.inertia * (self.kp_a * err - self.kd_a * rate)
            tilt = np.cos(ex) * np.cos(ez)
        else:
            th = st.e[0]
            want = np.clip(-acc[0] / self.g, -self.max_tilt, self.max_tilt)
            torque = self.inertia * (self.kp_a * (want - th - st.s @ self.wing)
                                     - self.kd_a * (st.e_dot + st.s_dot @ self.wing))
            tilt = np.cos(th)
        lift = self.mass * (self.g + acc[1]) / max(tilt, 0.5)
        return self.unmix @ np.r_[lift, torque]


@dataclass
class Segment:
    kind: str
    steps: int
    start: np.ndarray    # setpoint at the start
    end: np.ndarray      # setpoint at the end (ramped with a velocity feed-forward)
    excite: np.ndarray   # (steps, m) thrust offsets added to the pilot's command


def plan_flight(drone, rng, seconds: float, dt: float, manoeuvres, home, ground: float,
                amplitude: float) -> list[Segment]:
    """Segments in a random order, every listed manoeuvre once per cycle, until ``seconds``."""
    m, dim = drone.num_rotors, drone.dim
    hover = drone.fem.mass.sum() * 9.81 / m
    spin = spin_signs(drone)
    segs, used, pos = [], 0, np.array(home, dtype=float)
    total = int(round(seconds / dt))
    horizontal = [0, 2] if dim == 3 else [0]
    order = []
    while used < total:
        if not order:
            order = list(rng.permutation(list(manoeuvres)))
        kind = order.pop()
        n = int(round(rng.uniform(1.2, 2.0) / dt))
        excite = np.zeros((n, m))
        end = pos.copy()
        if kind == "steps":
            axis = rng.choice(horizontal + [1])
            end[axis] += rng.choice([-1, 1]) * rng.uniform(0.4, 0.8)
        elif kind == "random_holds":
            hold = int(round(0.3 / dt))
            for k in range(0, n, hold):
                excite[k:k + hold] = rng.uniform(-1, 1, m) * amplitude * hover
        elif kind == "ground_pass":
            end[1] = ground + rng.uniform(0.35, 0.6)
        elif kind == "differential":
            half = int(round(0.4 / dt))
            for k in range(0, n, half):
                excite[k:k + half] = spin * amplitude * hover * (1 if (k // half) % 2 == 0 else -1)
        elif kind == "high_speed":
            d = rng.normal(size=len(horizontal))
            d /= np.linalg.norm(d)
            end[horizontal] += d * rng.uniform(2.0, 3.0) * n * dt
        segs.append(Segment(kind, n, pos.copy(), end, excite))
        used += n
        # come back towards home between manoeuvres so flights stay compact and high enough
        pos = end if kind in ("steps", "high_speed") else pos
        if kind == "ground_pass" or np.linalg.norm(pos - home) > 4.0:
            segs.append(Segment("hover", int(round(1.0 / dt)), end, np.array(home, float), np.zeros((int(round(1.0 / dt)), m))))
            used += segs[-1].steps
            pos = np.array(home, float)
    return segs


def fly(sim, pilot: Pilot, segs: list[Segment], dt: float, settle: float = 1.0):
    """Fly the plan; returns (t, u, y) rows and the failure (None if the flight survived)."""
    from sdexp.sensing.rotations import euler_from_matrix  # noqa: F401  (pilot uses e directly)
    home = segs[0].start
    t_rows, u_rows, y_rows = [], [], []
    plan = [("settle", home, home, np.zeros(sim.drone.num_rotors))] * int(round(settle / dt))
    for s in segs:
        for k in range(s.steps):
            f = (k + 1) / s.steps
            target = s.start + min(1.0, 1.5 * f) * (s.end - s.start)
            plan.append((s.kind, target, (s.end - s.start) / (s.steps * dt / 1.5) if f < 1 / 1.5 else 0 * home, s.excite[k]))
    for kind, target, vel, excite in plan:
        st = sim.state()
        u = np.clip(pilot.act(st, target, vel) + excite, -sim.drone.max_thrust, sim.drone.max_thrust)
        t_rows.append(sim.t); u_rows.append(u); y_rows.append(state_row(st))
        sim.step(u)
        if not sim.alive:
            break
    return np.array(t_rows), np.array(u_rows), np.array(y_rows), sim.failure


def start_pose(drone, height: float) -> np.ndarray:
    """The offset that puts the drone's lowest vertex ``height`` above the ground plane at 0."""
    off = np.zeros(drone.dim)
    off[1] = height - drone.fem.rest[:, 1].min()
    return off


def record_flight(sim, pilot: Pilot, i: int, seed: int, seconds: float, manoeuvres, height: float, ground: float,
                  amplitude: float):
    """Flight ``i`` of a recording seeded ``seed``: its plan, noise and effect draws from (seed, i)
    alone, so the same flight can be flown again with other physics. Returns fly's rows."""
    drone, dt = sim.drone, sim.cfg.control_dt
    rng = np.random.default_rng([seed, i])
    sim.rng = np.random.default_rng([seed, i, 1])
    sim.reset(start_pose(drone, height), flight=i)   # the flight's random effects (gusts) drawn for flight i
    pilot.reset()
    home = sim.state(noisy=False).p
    return fly(sim, pilot, plan_flight(drone, rng, seconds, dt, manoeuvres, home, ground, amplitude), dt)


def manoeuvre_log(drone, sim_cfg, noise_cfg, effects: list, kind: str, seconds: float, seed: int, height: float,
                  ground: float, amplitude: float) -> np.ndarray:
    """The readings (rows in channel order) of flight 0 of a recording of one manoeuvre kind with
    ``effects``: the same kind, seed and noise fly the same plan whatever the effects."""
    from sdexp.sim.simulator import Simulator

    sim = Simulator(drone, sim_cfg, noise_cfg, seed=seed, effects=effects)
    pilot = Pilot(drone, sim.cfg.gravity, dt=sim.cfg.control_dt)
    return record_flight(sim, pilot, 0, seed, seconds, [kind], height, ground, amplitude)[2]


def record_flights(drone, sim_cfg, noise_cfg, out_dir: Path, flights: int, seconds: float,
                   manoeuvres, seed: int, height: float = 2.5, ground: float = 0.0,
                   amplitude: float = 0.3, effects=None, report=None, meta_extra=None) -> list[Path]:
    """Record ``flights`` logs into out_dir (meta.json + flight_XXX.csv). ``effects`` (entries)
    are the hidden physics; the logs do not say what they were unless meta_extra does."""
    from sdexp.sim.simulator import Simulator

    bad = [m for m in manoeuvres if m not in MANOEUVRES]
    if bad:
        raise UserError(f"record.manoeuvres: unknown {bad}; choose from {list(MANOEUVRES)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sim = Simulator(drone, sim_cfg, noise_cfg, seed=seed, effects=effects)
    dt = sim.cfg.control_dt
    pilot = Pilot(drone, sim.cfg.gravity, dt=dt)
    paths, failures = [], []
    for i in range(flights):
        t, u, y, failure = record_flight(sim, pilot, i, seed, seconds, manoeuvres, height, ground, amplitude)
        if failure is not None:
            failures.append(f"flight_{i:03d}: {failure.reason} at {failure.time:.2f} s")
        paths.append(write_flight(out_dir, f"flight_{i:03d}", t, u, y, drone.dim, drone.layout.n_s))
        if report:
            report(1)
    write_meta(out_dir, meta_for(drone, 1.0 / dt, **(meta_extra or {}), failures=failures))
    return paths
