"""Full-FEM snapshots for the reduced model's basis and cubature: open-loop flights of the drone
under random thrust holds (the two data recipes of sdexp.conf.data: the default near-hover holds
and the paper's +-Tmax holds), run on the full model's Body. Open loop because the simulator
sits below the controllers; controller flights enter only the gates (sdexp.eval.reduced_gates)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sdexp.sim.drone import Drone
from sdexp.sim.physics.fem import stable_substep
from sdexp.sim.physics.integrator import Body, extent


@dataclass(frozen=True)
class Recipe:
    """Every rotor holds ``centre + U[-spread, spread] x Tmax`` for ``hold`` s; an episode from
    rest lasts ``episode`` s or until the body fails. ``centre``: "hover" (the rest shape's hover
    thrust, weight shared evenly) or "zero"."""
    name: str
    centre: str
    spread: float
    hold: float
    episode: float


NEAR_HOVER = Recipe("near_hover", "hover", 0.3, 0.1, 4.0)   # sdexp/conf/data/near_hover.yaml
PAPER = Recipe("paper", "zero", 1.0, 1.0, 10.0)              # sdexp/conf/data/paper.yaml (shorter episodes)
RECIPES = {r.name: r for r in (NEAR_HOVER, PAPER)}


def hover_thrust(drone: Drone, gravity: float) -> float:
    """Each rotor's share of the weight, along its rest normal's vertical part (at least 0.3)."""
    up = np.clip(drone.rotors.normals[:, 1], 0.3, None)
    return float(drone.fem.mass.sum() * gravity / up.sum())


def holds(drone: Drone, recipe: Recipe, steps: int, rng: np.random.Generator, gravity: float = 9.81,
          control_dt: float = 0.01) -> np.ndarray:
    """(steps, m) thrust commands: the recipe's holds, each rotor redrawn every ``recipe.hold`` s."""
    centre = hover_thrust(drone, gravity) if recipe.centre == "hover" else 0.0
    tmax = drone.max_thrust
    per_hold = max(1, int(round(recipe.hold / control_dt)))
    draws = centre + rng.uniform(-recipe.spread, recipe.spread, (-(-steps // per_hold), drone.num_rotors)) * tmax
    return np.clip(np.repeat(draws, per_hold, axis=0)[:steps], -tmax, tmax)


def flights(drone: Drone, recipe: Recipe, seconds: float, seed: int, gravity: float = 9.81,
            control_dt: float = 0.01, every: int = 2, safety: float = 0.8):
    """Positions (S, nv, dim) every ``every`` control steps of ``seconds`` of open-loop holds. A state that blows up (inverted element, non-finite,
    stretched past 4x) is dropped with its episode's rest."""
    fem = drone.fem
    rng = np.random.default_rng(seed)
    dt = stable_substep(fem, safety)
    n_sub = int(np.ceil(control_dt / dt - 1e-9))
    dt = control_dt / n_sub
    per_episode = max(1, int(round(recipe.episode / control_dt)))
    rest_size = extent(fem.rest)
    xs = []
    steps = int(round(seconds / control_dt))
    k = 0
    while k < steps:
        body = Body(fem, 1, drone.rotors)
        for u in holds(drone, recipe, per_episode, rng, gravity, control_dt):
            inverted, vmax2 = body.run(n_sub, dt, u, drone.damping, gravity, drone.deformation_damping)
            k += 1
            if inverted > 0 or not np.isfinite(vmax2) or extent(body.x) > 4 * rest_size:
                break
            if k % every == 0:
                xs.append(body.x.copy())
            if k >= steps:
                break
    return np.array(xs)
