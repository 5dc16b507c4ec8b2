"""Bends a drone's rotors can hold: open loop, noise-free, under a thrust pattern that puts no net
lift or tilting torque on the rest shape (geometry.deformation_patterns: the body hovers roughly
level and only deforms).

Used as a yardstick of the body itself, apart from any controller: the obstacle experiment's
fold limit (how far the star's wings can fold at all), and bench_sim's accuracy column (how much
a petal bends under a fixed load at each mesh resolution: coarse linear tets are too stiff)."""
from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf

from sdexp.sim.geometry import deformation_patterns, rest_hover_thrust, rigid_body
from sdexp.sim.sensors import decompose
from sdexp.sim.simulator import Simulator


def outer_rotors(drone, along_z: bool = False) -> np.ndarray:
    """Mask of the rotors beyond half the largest rotor reach from the centre (in X-Z); with
    ``along_z`` only those nearer the Z axis than the X axis (the star's folding wings)."""
    fem = drone.fem
    _, _, _, pos, _ = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    reach = np.linalg.norm(pos[:, [0, 2]], axis=1) if fem.dim == 3 else np.abs(pos[:, 0])
    mask = reach > 0.5 * reach.max()
    if along_z:
        mask &= np.abs(pos[:, 2]) > np.abs(pos[:, 0])
    return mask


def held_bend(drone, sim_cfg, noise_cfg, rotors: np.ndarray, amplitude: float | None = None,
              seconds: float = 3.0) -> np.ndarray:
    """Bend angles s (deg, one per peripheral sensor) after ``seconds`` of hover thrust plus the
    deformation pattern nearest to pushing the masked ``rotors`` up, its largest rotor offset
    ``amplitude`` (N; None: as large as +-Tmax allows on top of hover)."""
    null = deformation_patterns(drone)
    pattern = null @ (null.T @ rotors.astype(float))
    if not np.abs(pattern).max() > 1e-9:
        raise ValueError(f"drone {drone.name}: those rotors cannot push without a net lift or tilting torque")
    pattern /= np.abs(pattern).max()
    hover, tmax = rest_hover_thrust(drone, float(sim_cfg.gravity)), drone.max_thrust
    if amplitude is None:
        room = np.where(pattern > 0, tmax - hover, -tmax - hover) / np.where(pattern == 0, np.inf, pattern)
        amplitude = room[pattern != 0].min()
    u = hover + amplitude * pattern
    sim = Simulator(drone, OmegaConf.merge(sim_cfg, {"obstacles": []}),
                    OmegaConf.merge(noise_cfg, {"enabled": False}), seed=0)
    r = sim.reset()
    for _ in range(int(round(seconds / float(sim_cfg.control_dt)))):
        r = sim.step(u)
        if not sim.alive:
            break
    return np.rad2deg(decompose(r, drone.layout).s)
