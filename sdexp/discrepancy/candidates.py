"""The candidate effects the workflow fits, each with the few parameters it estimates.

Each candidate is parametrised so that theta = 0 is the nominal simulator and the predicted
channels move about linearly in theta over the strengths that matter (ground effect in R^2,
stiffness as a compliance change, wind as the dynamic-pressure vector |w| w, payload as mass
and first moments): one finite-difference Jacobian then fits well, and a second Gauss-Newton
step (chord) corrects what is left. Where no parametrisation is near-linear over the range
(stiffness: its strong changes shift the bending frequencies, so the predicted oscillations
move out of phase; a delay shifts whole responses in time) a coarse ``scan`` of theta values
picks where the finite differences are taken. ``options`` are discrete choices fitted by
enumeration (which rotor lost thrust).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from sdexp.sim.physics.effects import LIBRARY
from sdexp.errors import UserError


@dataclass
class Candidate:
    name: str
    params: list[str]                    # fitted parameters (the theta the fit reports)
    steps: np.ndarray                    # finite-difference steps: typical strengths
    lower: np.ndarray
    upper: np.ndarray
    build: Callable                      # (theta, option) -> list of effect entries
    report: Callable                     # (theta, option) -> dict of physical parameters
    options: list = field(default_factory=lambda: [None])
    base: Callable | None = None         # option -> entries at theta = 0 when not nominal
    anchor: np.ndarray | None = None     # where the other columns are differenced (payload: a mass)
    scan: list | None = None             # theta values tried first; the best is linearised about


def library_candidates(drone, names=None) -> list[Candidate]:
    dim, m = drone.dim, drone.num_rotors
    centre = drone.fem.mass @ drone.fem.rest / drone.fem.mass.sum()
    horiz = [0, 2] if dim == 3 else [0]
    hn = ["x", "z"] if dim == 3 else ["x"]
    a = np.array

    def vec(parts, dim_idx, n=dim):
        v = np.zeros(n)
        v[dim_idx] = parts
        return v.tolist()

    cands = {
        "rotor_reaction_torque": Candidate(
            "rotor_reaction_torque", ["k"], a([0.02]), a([-0.5]), a([0.5]),
            lambda th, o: [{"name": "rotor_reaction_torque", "k": float(th[0])}],
            lambda th, o: {"k": float(th[0])}),
        "rotor_drag": Candidate(
            "rotor_drag", ["k"], a([0.1]), a([0.0]), a([5.0]),   # a drag never pushes: k >= 0
            lambda th, o: [{"name": "rotor_drag", "k": float(th[0])}],
            lambda th, o: {"k": float(th[0])}),
        "quadratic_drag": Candidate(
            "quadratic_drag", ["c"], a([0.03]), a([-0.2]), a([2.0]),
            lambda th, o: [{"name": "quadratic_drag", "c": float(th[0])}] if th[0] >= 0 else
            [{"name": "quadratic_drag", "c": 0.0}],
            lambda th, o: {"c": float(th[0])}),
        "ground_effect": Candidate(
            "ground_effect", ["radius_sq"], a([1.0]), a([0.0]), a([9.0]),
            lambda th, o: [{"name": "ground_effect", "radius": float(np.sqrt(max(th[0], 0.0)))}],
            lambda th, o: {"radius": float(np.sqrt(max(th[0], 0.0)))}),
        "motor_lag": Candidate(
            "motor_lag", ["tau"], a([0.03]), a([0.0]), a([0.5]),
            lambda th, o: [{"name": "motor_lag", "tau": float(max(th[0], 0.0))}],
            lambda th, o: {"tau": float(th[0])}),
        "actuation_delay": Candidate(
            "actuation_delay", ["delay"], a([0.02]), a([0.0]), a([0.3]),
            lambda th, o: [{"name": "actuation_delay", "delay": float(max(th[0], 0.0))}],
            lambda th, o: {"delay": float(th[0])}, scan=[a([0.03]), a([0.06]), a([0.12])]),
        "thrust_loss": Candidate(
            "thrust_loss", ["fraction"], a([0.1]), a([0.0]), a([0.9]),
            lambda th, o: [{"name": "thrust_loss", "rotor": int(o), "fraction": float(th[0])}],
            lambda th, o: {"rotor": int(o), "fraction": float(th[0])}, options=list(range(m))),
        "payload": Candidate(
            "payload", ["mass", *[f"mass_{n}" for n in hn]], a([0.1] + [0.05] * len(hn)),
            a([0.0] + [-2.0] * len(hn)), a([2.0] + [2.0] * len(hn)),
            lambda th, o: _payload(th, centre, horiz),
            lambda th, o: {"mass": float(th[0]),
                           "point": (centre + vec(th[1:] / max(th[0], 1e-9), horiz)).tolist()},
            anchor=a([0.1] + [0.0] * len(hn))),
        "stiffness_scale": Candidate(
            "stiffness_scale", ["compliance"], a([0.2]), a([-0.8]), a([4.0]),
            lambda th, o: [{"name": "stiffness_scale", "scale": float(1.0 / (1.0 + th[0]))}],
            lambda th, o: {"scale": float(1.0 / (1.0 + th[0]))},
            scan=[a([2.0 ** -(j / 4) - 1.0]) for j in (-4, -3, -2, -1, 1, 2, 3, 4)]),   # scale 2^(j/4)
        "damping_scale": Candidate(
            "damping_scale", ["excess"], a([0.3]), a([-1.0]), a([9.0]),
            lambda th, o: [{"name": "damping_scale", "scale": float(max(1.0 + th[0], 0.0))}],
            lambda th, o: {"scale": float(1.0 + th[0])}),
        "wind": Candidate(
            "wind", [f"q_{n}" for n in hn], a([1.0] * len(hn)), a([-25.0] * len(hn)), a([25.0] * len(hn)),
            lambda th, o: [{"name": "wind", "velocity": vec(_speed(th), horiz)}],
            lambda th, o: {"velocity": vec(_speed(th), horiz)},
            base=lambda o: [{"name": "wind", "velocity": [0.0] * dim}]),
        "imu_bias": Candidate(
            "imu_bias", ["tilt_x", "tilt_z"] if dim == 3 else ["tilt"], a([0.01] * (2 if dim == 3 else 1)),
            a([-0.2] * (2 if dim == 3 else 1)), a([0.2] * (2 if dim == 3 else 1)),
            lambda th, o: [{"name": "imu_bias", "channel": "rot",
                            "value": vec(th, [0, 2], 3) if dim == 3 else [float(th[0])]}],
            lambda th, o: {"channel": "rot", "value": vec(th, [0, 2], 3) if dim == 3 else [float(th[0])]}),
    }
    if dim == 2:
        cands.pop("rotor_reaction_torque")   # a 2D rotor axis lies in the plane
    if names:
        unknown = [n for n in names if n not in LIBRARY]
        if unknown:
            raise UserError(f"discrepancy.candidates: unknown {unknown}; choose from {sorted(LIBRARY)}")
        return [cands[n] for n in names if n in cands]
    return list(cands.values())


def _speed(q: np.ndarray) -> np.ndarray:
    """w from the dynamic-pressure vector q = |w| w."""
    n = np.linalg.norm(q)
    return q / np.sqrt(n) if n > 0 else np.zeros_like(q)


def _payload(th, centre, horiz):
    mass = float(max(th[0], 0.0))
    point = np.array(centre, dtype=float)
    if mass > 0:
        point[horiz] += th[1:] / mass
    return [{"name": "payload", "mass": mass, "point": point.tolist()}]
