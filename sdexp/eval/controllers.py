"""The controllers by name (``CONTROLLERS``), each built from a config, a simulator and the learned
model: the paper's four, and where a new one is registered.

The rigid baselines get their privileged geometry here, from the simulator's mesh: the rest
shape once (rigid LQR) or the deformed shape at every control step (geometry-updating LQR), in
the body frame the frame IMU defines. Everything else flows through the sensor readings.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from sdexp.control.controller import Controller
from sdexp.control.lowpass import LowPassed
from sdexp.control.lqr import regulated_states, state_weights
from sdexp.control.neural import NeuralController, load_or_train_policy
from sdexp.control.relinearizing import RelinearizingLQR
from sdexp.control.rigid import RigidGeometry, RigidLQR
from sdexp.sim.rigid.geometry import rigid_body, rotation_2d
from sdexp.sensing.rotations import exp_so3, matrix_from_euler
from sdexp.sim.simulator import Simulator


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
                            regulated=None if len(regulated) == len(q) else regulated,
                            q_alike=float(c.q_s_alike), velocity_scale=float(c.velocity_scale),
                            max_rate=max_feedback_rate(cfg), r_alike=float(c.r_alike),
                            share_pull=float(c.share_pull), integral=float(c.integral),
                            approach_speed=c.approach_speed, **kw)


def max_feedback_rate(cfg) -> float | None:
    """control.delay_phase_deg over the command delay, in rad/s (None: no bound)."""
    phase, delay = cfg.control.delay_phase_deg, int(cfg.model.command_delay)
    return None if phase is None else float(np.radians(phase)) / (delay * float(cfg.sim.control_dt))


def state_sizes_of(dyn) -> dict[str, int]:
    return {"n_s": dyn.n_s, "n_e": dyn.n_e, "dim": dyn.dim, "m": dyn.m}


def _ours(cfg, sim: Simulator, dyn, **_) -> RelinearizingLQR:
    return ours(cfg, dyn, sim.drone.max_thrust)


def _rigid_lqr(cfg, sim: Simulator, **_) -> RigidLQR:
    c, geom = cfg.control, geometry_of(sim, rest=True)
    return RigidLQR(lambda: geom, c.q_e, c.q_p, c.velocity_scale, c.r, float(cfg.sim.gravity), name="rigid_lqr",
                    dt=riccati_step(cfg))


def _geometry_lqr(cfg, sim: Simulator, **_) -> RigidLQR:
    c = cfg.control
    return RigidLQR(lambda: geometry_of(sim, rest=False), c.q_e, c.q_p, c.velocity_scale, c.r, float(cfg.sim.gravity),
                    update_every=1, name="geometry_lqr", dt=riccati_step(cfg))


def _reduced_lqr(cfg, sim: Simulator, **_):
    """The privileged reduced-model LQR (sdexp.control.modal_lqr): the flown simulator's reduced
    model (sim.model = reduced) or the drone's reduced model built from sim.reduced (the full
    model flown: its mesh observed through the best-fit frame and the projected deformation)."""
    from sdexp.control.modal_lqr import ModalLQR
    from sdexp.sim.reduced.body import reduced_stiffness, stable_substep
    from sdexp.sim.reduced.linear import Linearization
    from sdexp.sim.reduced.model import build_reduced, spec_of
    from sdexp.sim.physics.native import default_cache_dir
    from sdexp.sim.reduced.snapshots import hover_thrust

    drone, c = sim.drone, cfg.control
    model = sim.reduced if sim.reduced is not None else build_reduced(
        drone, spec_of(cfg.sim.reduced), str(default_cache_dir()), float(cfg.sim.gravity), float(cfg.sim.control_dt))
    lin = Linearization(model, stable_substep(model, float(cfg.sim.stability_safety)), drone.damping,
                        drone.deformation_damping, float(cfg.sim.gravity))
    if sim.reduced is not None:
        def observe():
            return lin.of_body(sim.body)
    else:
        def observe():
            return lin.of_nodes(sim.x, sim.v)
    x0 = observe()
    R0 = exp_so3(x0[lin.slices["phi"]])
    p = np.zeros(3)
    p[:drone.dim] = sim.state(noisy=False).p
    offset = R0.T @ (p - x0[lin.slices["c"]])   # the measured point (frame IMU) from the centre of mass
    # the even share of the weight: where the design's thrust rests in the directions the rigid
    # motion does not feel (the least-norm split loads a plate's tips alone and folds a soft one)
    u_rest = np.full(drone.num_rotors, hover_thrust(drone, float(cfg.sim.gravity)))
    K0 = reduced_stiffness(model)
    _, modes = np.linalg.eigh(0.5 * (K0 + K0.T))
    return ModalLQR(observe, lin.jacobians, modes, int(cfg.sim.reduced.linear_modes), u_rest, offset, c.q_p, c.q_e,
                    c.velocity_scale, c.r, c.n, c.kp, c.waypoint_max, planar=drone.dim == 2)


def _neural(cfg, sim: Simulator, dyn, data, trained, progress: bool, **_) -> NeuralController:
    a = data.arrays
    x = np.concatenate([np.asarray(a[k]).reshape(len(a[k]), -1) for k in ("s", "s_dot", "e", "e_dot", "p", "p_dot")], 1)
    policy, _ = load_or_train_policy(dyn, x, sim.drone.max_thrust, cfg.control.neural, int(cfg.seed), trained.key,
                                     cfg.cache_dir, progress)
    return NeuralController(policy)


# name -> builder(cfg, sim, dyn=, data=, trained=, progress=): the controller (its ``name`` is
# this key), configured by ``cfg.control``; a builder takes what it needs and ignores the rest.
# The names an experiment's ``controllers`` may list, checked before a run starts
# (sdexp.eval.run.check_names). A new controller: its class (the Controller protocol)
# and one line here.
CONTROLLERS: dict[str, Callable[..., Controller]] = {
    "ours": _ours, "rigid_lqr": _rigid_lqr, "geometry_lqr": _geometry_lqr, "neural": _neural,
    "reduced_lqr": _reduced_lqr,   # privileged: it observes the frame and modal coordinates
}


# the controllers that fly on the learned model (the rest need no data or training)
LEARNED = ("ours", "neural")


def build(name: str, cfg, sim: Simulator, dyn=None, data=None, trained=None, progress: bool = True) -> Controller:
    """The controller registered as ``name``, for a flight of ``sim``; with ``control.lowpass`` > 0
    it reads the state through that low-pass (every controller alike)."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}: choose from {', '.join(CONTROLLERS)}")
    controller = CONTROLLERS[name](cfg, sim, dyn=dyn, data=data, trained=trained, progress=progress)
    tau = float(cfg.control.lowpass)
    return LowPassed(controller, tau, float(cfg.sim.control_dt)) if tau > 0 else controller
