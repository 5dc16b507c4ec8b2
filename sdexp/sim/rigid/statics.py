"""What a drone's rotors hold open loop, noise-free: bends under a thrust pattern that puts no net
lift or tilting torque on the rest shape (geometry.deformation_patterns: the body hovers roughly
level and only deforms), and the hover thrust that keeps the rest shape best.

Yardsticks of the body itself, apart from any controller: the obstacle experiment's fold limit
(how far the star's wings can fold at all) and bench_sim's accuracy column (how much a petal
bends under a fixed load at each mesh resolution: coarse linear tets are too stiff). The
shape-holding hover is the centre of the data recipe's draw with ``data.hover: shape``."""
from __future__ import annotations

from dataclasses import dataclass, replace

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


# ---------------------------------------------------------------------------------- static hover
# The design rule (docs/designs.md): where the paper leaves a design open (a rotor layout, a
# thickness), the design must hover statically with margin, checked here and nowhere near a
# controller. Constants of the rule:
RULE_MAX_SHARE = 0.6       # the static hover's largest rotor thrust, of Tmax: 40% left to steer with
RULE_MAX_FOLD_DEG = 45.0   # the largest bend the body settles at under it (half-way to a right angle)
RULE_MAX_SWING_DEG = 1.0   # ... moving no more than this over the hold's last second (settled)
RULE_MAX_RESIDUAL = 0.02   # the settled shape's lift off the weight, and its tilting torque off zero
                           # (over weight x the rotors' largest reach), at most this

STATIC_HOVER_FORMAT = 1    # bump when static_hover (or the simulation it holds) changes what it finds
_SCALARS = ("share", "fold_deg", "swing_deg", "lift_residual", "torque_residual")


@dataclass(frozen=True)
class StaticHover:
    """What ``static_hover`` finds: the thrust, whether the simulation stayed sane (else ``reason``),
    the largest rotor's share of Tmax, the settled largest bend (deg, mean over the hold's last
    second) and its swing over that second, the lift's residual (of the weight) and the tilting
    torque's (of weight x reach)."""
    thrust: np.ndarray
    sane: bool
    reason: str
    share: float
    fold_deg: float
    swing_deg: float
    lift_residual: float
    torque_residual: float

    def rule(self) -> str:
        """"" when the design rule holds, else which of its bounds this hover breaks (the first)."""
        if not self.sane:
            return self.reason
        for name, value, bound in (("largest rotor thrust", self.share, RULE_MAX_SHARE),
                                   ("settled fold", self.fold_deg, RULE_MAX_FOLD_DEG),
                                   ("fold's swing over the last second", self.swing_deg, RULE_MAX_SWING_DEG),
                                   ("lift residual", self.lift_residual, RULE_MAX_RESIDUAL),
                                   ("tilting torque residual", self.torque_residual, RULE_MAX_RESIDUAL)):
            if not value <= bound:
                unit = " of Tmax" if name.startswith("largest") else (" deg" if "fold" in name else "")
                return f"{name} {value:.3g}{unit} > {bound:g}{unit}"
        return ""

    def arrays(self) -> dict:
        """For the cache (``cached_arrays``)."""
        return {"thrust": self.thrust, "sane": np.array(self.sane), "reason": np.array(self.reason),
                **{k: np.array(getattr(self, k)) for k in _SCALARS}}

    def row(self) -> dict:
        return {"static_hover_share": self.share, "static_hover_fold_deg": self.fold_deg,
                "static_hover_swing_deg": self.swing_deg, "static_hover_lift_residual": self.lift_residual,
                "static_hover_torque_residual": self.torque_residual, "design_rule": self.rule() or "holds"}


def static_hover(drone, sim_cfg, seconds: float = 10.0, settle: float = 1.0, trim_every: int = 10,
                 gain: float = 0.2, cache_dir=None) -> StaticHover:
    """The static hover of the deformed body: the shape-holding hover thrust (``shape_hover_thrust``),
    scaled until the shape it bends the body into lifts the weight, held ``seconds`` on the full
    FEM with the body's rigid motion taken out after every control step (inertia relief: the
    body is held where it is and only deforms). A hold released free falls or tips over (an open
    loop hover is unstable), so it cannot tell a shape that holds from one that does not; here
    what is left is statics: whether the thrust lifting the weight leaves a settled, bounded fold
    within the rotors' range. The lift is trimmed every ``trim_every`` control steps by ``gain``
    of its relative error (a slow trim: a fast one, or one on the torques too, rings with the
    petals of the orange peel). With ``cache_dir``, found once per body and simulator config."""
    if cache_dir is None:
        return _static_hover(drone, sim_cfg, seconds, settle, trim_every, gain, None)
    key = key_of("statichover", STATIC_HOVER_FORMAT,
                 {"body": content_digest(drone), "sim": content_digest(sim_cfg), "seconds": seconds,
                  "settle": settle, "trim_every": trim_every, "gain": gain})
    a = cached_arrays(cache_dir, key, lambda: _static_hover(drone, sim_cfg, seconds, settle, trim_every, gain,
                                                            cache_dir).arrays())
    return StaticHover(a["thrust"], bool(a["sane"]), str(a["reason"]), *(float(a[k]) for k in _SCALARS))


def _without_rigid_velocity(x: np.ndarray, v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """v less the rigid motion (the mass-weighted mean velocity and the angular velocity of the
    nodes' angular momentum about their centre of mass)."""
    total = m.sum()
    r = x - m @ x / total
    vc = m @ v / total
    dv = v - vc
    if x.shape[1] == 3:
        inertia = np.eye(3) * np.einsum("i,ij,ij->", m, r, r) - np.einsum("i,ij,ik->jk", m, r, r)
        w = np.linalg.solve(inertia, np.einsum("i,ij->j", m, np.cross(r, dv)))
        return dv - np.cross(w, r)
    w = (m @ (r[:, 0] * dv[:, 1] - r[:, 1] * dv[:, 0])) / (m @ (r * r).sum(axis=1))
    return dv - w * np.c_[-r[:, 1], r[:, 0]]


def _static_hover(drone, sim_cfg, seconds, settle, trim_every, gain, cache_dir) -> StaticHover:
    from sdexp.sim.rigid.geometry import wrench_matrix

    fem, dim = drone.fem, drone.fem.dim
    weight = float(fem.mass.sum()) * float(sim_cfg.gravity)
    u = shape_hover_thrust(drone, sim_cfg, cache_dir=cache_dir)
    # the full FEM: its velocities are the nodes' own, to take the rigid motion out of
    sim = Simulator(drone, replace(sim_cfg, obstacles=[], model="full"), NoiseConfig(enabled=False), seed=0)
    sim.reset()
    dt = float(sim_cfg.control_dt)
    steps, keep = max(1, int(round(seconds / dt))), max(1, int(round(settle / dt)))
    tilt = [3, 5] if dim == 3 else [2]
    folds = []
    for k in range(steps):
        s = decompose(sim.step(u), drone.layout).s
        if not sim.alive:
            fold = f", folded {folds[-1]:.0f} deg" if folds else ""
            return StaticHover(u, False, f"the hold failed at {(k + 1) * dt:.2f} s ({sim.failure.reason}{fold})",
                               *([np.nan] * len(_SCALARS)))
        sim.body.v[:] = _without_rigid_velocity(sim.x, sim.v, fem.mass)
        folds.append(float(np.rad2deg(np.abs(s)).max()) if s.size else 0.0)
        if (k + 1) % trim_every == 0 or k == steps - 1:
            _, _, _, pos, dirs = rigid_body(sim.x, fem.mass, drone.rotors, np.eye(dim))
            W = wrench_matrix(pos, dirs)
            lift = float(W[1] @ u)
            if k < steps - 1 and lift > 0:
                u = np.clip(u * (1.0 + gain * (weight / lift - 1.0)), -drone.max_thrust, drone.max_thrust)
    reach = float(np.linalg.norm(pos, axis=1).max())
    last = np.array(folds[-keep:])
    return StaticHover(u, True, "", float(np.abs(u).max() / drone.max_thrust), float(last.mean()),
                       float(last.max() - last.min()), abs(lift - weight) / weight,
                       float(np.linalg.norm(W[tilt] @ u)) / (weight * reach))
