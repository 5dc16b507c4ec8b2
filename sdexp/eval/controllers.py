"""Building the four controllers of the paper from a config, a simulator and the learned model.

The rigid baselines get their privileged geometry here, from the simulator's mesh: the rest
shape once (rigid LQR) or the deformed shape at every control step (geometry-updating LQR), in
the body frame the frame IMU defines. Everything else flows through the sensor readings.
"""
from __future__ import annotations

import numpy as np

from sdexp.control.lqr import regulated_states, state_weights
from sdexp.control.neural import NeuralController, load_or_train_policy
from sdexp.control.relinearizing import RelinearizingLQR
from sdexp.control.rigid import RigidGeometry, RigidLQR
from sdexp.sim.rigid.geometry import rigid_body, rotation_2d
from sdexp.sensing.rotations import matrix_from_euler
from sdexp.sim.simulator import Simulator

CONTROLLERS = ("ours", "rigid_lqr", "geometry_lqr", "neural")


def geometry_of(sim: Simulator, rest: bool) -> RigidGeometry:
    fem = sim.drone.fem
    if rest:
        points, R = fem.rest, np.eye(fem.dim)
    else:
        e = sim.state(noisy=False).e
        points, R = sim.x, (matrix_from_euler(e) if fem.dim == 3 else rotation_2d(e[0]))
    mass, _, inertia, pos, dirs = rigid_body(points, fem.mass, sim.drone.rotors, R)
    return RigidGeometry(mass, inertia, pos, dirs)


def riccati_step(cfg) -> float | None:
    """None for the paper's continuous Riccati gain, the control interval for the sampled one."""
    return float(cfg.sim.control_dt) if cfg.control.riccati == "discrete" else None


def ours(cfg, dyn, max_thrust: float, **kw) -> RelinearizingLQR:
    c = cfg.control
    sizes = state_sizes_of(dyn)
    q = state_weights(sizes, c.q_s, c.q_e, c.q_p, c.velocity_scale, c.q_p_axes, c.q_e_axes)
    noise = np.radians(float(cfg.noise.angle_std_deg)) if cfg.noise.enabled else 0.0
    regulated = regulated_states(sizes, getattr(dyn, "bend_spread", None), noise, float(c.bend_snr))
    return RelinearizingLQR(dyn, q, c.r, c.kp, c.kd, c.n, max_thrust, dt=riccati_step(cfg),
                            feedforward=bool(c.feedforward), waypoint_max=c.waypoint_max,
                            regulated=None if len(regulated) == len(q) else regulated, **kw)


def state_sizes_of(dyn) -> dict[str, int]:
    return {"n_s": dyn.n_s, "n_e": dyn.n_e, "dim": dyn.dim, "m": dyn.m}


def build(name: str, cfg, sim: Simulator, dyn=None, data=None, trained=None, progress: bool = True):
    """One of CONTROLLERS, configured by ``cfg.control``."""
    c, g = cfg.control, float(cfg.sim.gravity)
    if name == "ours":
        return ours(cfg, dyn, sim.drone.max_thrust)
    if name == "rigid_lqr":
        geom = geometry_of(sim, rest=True)
        return RigidLQR(lambda: geom, c.q_e, c.q_p, c.velocity_scale, c.r, g, name=name, dt=riccati_step(cfg))
    if name == "geometry_lqr":
        return RigidLQR(lambda: geometry_of(sim, rest=False), c.q_e, c.q_p, c.velocity_scale, c.r, g,
                        update_every=1, name=name, dt=riccati_step(cfg))
    if name == "neural":
        a = data.arrays
        x = np.concatenate([np.asarray(a[k]).reshape(len(a[k]), -1) for k in ("s", "s_dot", "e", "e_dot", "p", "p_dot")], 1)
        policy, _ = load_or_train_policy(dyn, x, sim.drone.max_thrust, c.neural, int(cfg.seed), trained.key,
                                         cfg.cache_dir, progress)
        return NeuralController(policy)
    raise ValueError(f"unknown controller {name!r}: choose from {CONTROLLERS}")
