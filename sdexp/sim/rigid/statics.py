"""What a drone's rotors hold open loop, noise-free: bends under a thrust pattern that puts no net
lift or tilting torque on the rest shape (geometry.deformation_patterns: the body hovers roughly
level and only deforms), and the hover thrust that keeps the rest shape best.

Yardsticks of the body itself, apart from any controller: the obstacle experiment's fold limit
(how far the star's wings can fold at all) and bench_sim's accuracy column (how much a petal
bends under a fixed load at each mesh resolution: coarse linear tets are too stiff). The
shape-holding hover is the centre of the data recipe's draw with ``data.hover: shape``."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from sdexp.cache import cached_arrays, content_digest, key_of
from sdexp.config import NoiseConfig
from sdexp.sim.rigid.geometry import deformation_patterns, rest_hover_thrust, rigid_body
from sdexp.sensing import decompose
from sdexp.sim.simulator import Simulator


def outer_rotors(drone, along_z: bool = False) -> np.ndarray:
    """Mask of the rotors beyond half the largest rotor reach from the centre (in X-Z); with
    ``along_z`` only those nearer the Z axis than the X axis (the star's folding wings)."""
    fem = drone.fem
    _, _, _, pos, _ = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    reach = np.linalg.norm(pos[:, [0, 2]], axis=1) if fem.dim == 3 else np.abs(pos[:, 0])
    mask = reach > 0.501 * reach.max()   # a rotor at exactly half the reach (the rod's) is inner, not a rounding tie
    if along_z:
        mask &= np.abs(pos[:, 2]) > np.abs(pos[:, 0])
    return mask


def hold_trace(drone, sim_cfg, u: np.ndarray, seconds: float) -> tuple[list, bool]:
    """(the decomposed state at release and after every control step of holding thrust ``u`` for
    ``seconds`` from rest, whether the simulation stayed sane), noise-free, no output delay; a
    hold that fails ends at the step that failed."""
    sim = Simulator(drone, replace(sim_cfg, obstacles=[]), NoiseConfig(enabled=False), seed=0)
    states = [decompose(sim.reset(), drone.layout)]
    for _ in range(int(round(seconds / float(sim_cfg.control_dt)))):
        states.append(decompose(sim.step(u), drone.layout))
        if not sim.alive:
            break
    return states, sim.alive


def hold_state(drone, sim_cfg, u: np.ndarray, seconds: float):
    """(decomposed state at release, after holding thrust ``u`` for ``seconds`` from rest, whether
    the simulation stayed sane), noise-free."""
    states, sane = hold_trace(drone, sim_cfg, u, seconds)
    return states[0], states[-1], sane


def hold(drone, sim_cfg, u: np.ndarray, seconds: float) -> np.ndarray:
    """Bend angles s (rad) after holding thrust ``u`` for ``seconds`` from rest, noise-free."""
    return hold_state(drone, sim_cfg, u, seconds)[1].s


def held_bend(drone, sim_cfg, rotors: np.ndarray, amplitude: float | None = None,
              seconds: float = 3.0) -> np.ndarray:
    """Bend angles s (deg, one per peripheral sensor) after ``seconds`` of hover thrust plus the
    deformation pattern nearest to pushing the masked ``rotors`` up, its largest rotor offset
    ``amplitude`` (N; None: as large as +-Tmax allows on top of hover)."""
    null = deformation_patterns(drone)
    pattern = null @ (null.T @ rotors.astype(float))
    if not np.abs(pattern).max() > 1e-9:
        raise ValueError(f"drone {drone.name}: those rotors cannot push without a net lift or tilting torque")
    return np.rad2deg(hold(drone, sim_cfg, _pattern_thrust(drone, sim_cfg, pattern, amplitude), seconds))


def _pattern_thrust(drone, sim_cfg, pattern: np.ndarray, amplitude: float | None = None) -> np.ndarray:
    """Hover thrust of the rest shape plus ``pattern`` scaled to a largest rotor offset of
    ``amplitude`` (N; None: as large as +-Tmax allows on top of hover)."""
    pattern = pattern / np.abs(pattern).max()
    hover, tmax = rest_hover_thrust(drone, float(sim_cfg.gravity)), drone.max_thrust
    if amplitude is None:
        room = np.where(pattern > 0, tmax - hover, -tmax - hover) / np.where(pattern == 0, np.inf, pattern)
        amplitude = room[pattern != 0].min()
    return hover + amplitude * pattern


def deform_reach(drone, sim_cfg, seconds: float = 2.0) -> float:
    """The largest bend (deg, any peripheral sensor) that one deformation pattern (a basis vector
    of ``deformation_patterns``, either sign) holds after ``seconds`` open loop, noise-free, at the
    largest amplitude +-Tmax leaves on top of the rest shape's hover thrust: how far the rotors
    can bend the body at all while it stays level (0: no pattern, or no sensor)."""
    if drone.layout.n_s == 0:
        return 0.0
    best = 0.0
    for pattern in deformation_patterns(drone).T:
        for sign in (1.0, -1.0):
            best = max(best, float(np.abs(hold(drone, sim_cfg, _pattern_thrust(drone, sim_cfg, sign * pattern),
                                               seconds)).max()))
    return float(np.rad2deg(best))


def rotor_compliance(drone, sim_cfg, u: np.ndarray, seconds: float = 1.0, step: float = 0.5) -> np.ndarray:
    """How far each rotor alone bends the body: per rotor, the largest change of any bend (rad per
    N) after holding ``u`` plus ``step`` N on that rotor for ``seconds`` from rest, against ``u``
    alone, noise-free. One second lets most bodies settle (the octopus's arms: 14.4 deg/N at
    0.5 s and at 1 s; the flower's petals 8.0 and 8.8); the rod's ends and the orange peel's
    petals keep bending (25 -> 42 and 26 -> 56 deg/N), so there it is a lower bound."""
    s0 = hold(drone, sim_cfg, u, seconds)
    return np.array([np.abs(hold(drone, sim_cfg, u + step * np.eye(len(u))[i], seconds) - s0).max() / step
                     for i in range(len(u))])


SHAPE_HOVER_FORMAT = 1   # bump when shape_hover_thrust (or the simulation it holds) changes what it finds


def shape_hover_thrust(drone, sim_cfg, seconds: float = 2.0, iterations: int = 3, step: float = 0.1,
                       cache_dir=None) -> np.ndarray:
    """The rest-shape hover thrust plus the deformation pattern that keeps the bends smallest
    after ``seconds`` of holding it (Gauss-Newton on s over the pattern coefficients, finite
    differences of ``step`` N), within +-Tmax. The rigid hover thrust spreads the weight evenly
    over the rotors; a soft body's mass is not spread like its rotors, so that thrust bends it
    (the rod: its ends curl 54 deg in 1 s and it falls; with this thrust 10 deg).
    With ``cache_dir`` it is found once per body and simulator config (their content) and read
    from the cache after: the data recipe centres on it and the fleet's physics holds it again,
    for every seed, and it costs 3 x (patterns + 1) holds (the octopus: 21 of 2 s each)."""
    if cache_dir is None:
        return _shape_hover_thrust(drone, sim_cfg, seconds, iterations, step)
    key = key_of("shapehover", SHAPE_HOVER_FORMAT, {"body": content_digest(drone), "sim": content_digest(sim_cfg),
                                                    "seconds": seconds, "iterations": iterations, "step": step})
    return cached_arrays(cache_dir, key, lambda: {"u": _shape_hover_thrust(drone, sim_cfg, seconds, iterations, step)})["u"]


def _shape_hover_thrust(drone, sim_cfg, seconds: float, iterations: int, step: float) -> np.ndarray:
    u = rest_hover_thrust(drone, float(sim_cfg.gravity))
    null = deformation_patterns(drone)
    if null.shape[1] == 0 or drone.layout.n_s == 0:
        return u
    tmax = drone.max_thrust
    for _ in range(iterations):
        s0 = hold(drone, sim_cfg, u, seconds)
        J = np.stack([(hold(drone, sim_cfg, u + step * p, seconds) - s0) / step for p in null.T], 1)
        u = np.clip(u + null @ np.linalg.lstsq(J, -s0, rcond=None)[0], -tmax, tmax)
    return u
