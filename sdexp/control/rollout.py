"""One flight loop for every controller and task, and the one metric computation they share.

``fly`` releases the drone at the task's start, then every control step: readings -> decomposed
state -> controller -> command clipped to [-Tmax, Tmax] -> simulator. The episode ends early on
a simulator failure (blow-up) or a controller failure (no stabilising Riccati solution, a
non-finite command); either is recorded, never raised.

Metrics (README "Metrics"):
  survival_time   s flown before the episode ended (the full duration if it did not);
  final_error     m, |p - p_goal| at the last recorded step (noise-free readings);
  thrust_usage    N, sum over control steps and rotors of |commanded thrust| (clipped), the
                  paper's "thrust usage"; ``thrust_per_second`` divides it by survival_time.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from sdexp.control.lqr import LqrFailure
from sdexp.control.tasks import Task, wrap_angle
from sdexp.sim.sensors import State, decompose
from sdexp.sim.simulator import Simulator


@dataclass
class Flight:
    controller: str
    t: list = field(default_factory=list)       # time after each step (s)
    x: list = field(default_factory=list)       # noise-free state vectors after each step
    u: list = field(default_factory=list)       # commands (clipped), one per step
    goal: list = field(default_factory=list)    # goal state vectors at each step
    failure: str | None = None                  # reason the episode ended early
    failure_time: float | None = None

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(getattr(self, k)) for k in ("t", "x", "u", "goal")}


def fly(sim: Simulator, controller, task: Task, on_step=None) -> Flight:
    # the controllers' matrices are tiny (28 x 28 at most): BLAS threads only add hand-offs and
    # stall when the simulator's threads hold the cores
    with threadpool_limits(1, user_api="blas"):
        return _fly(sim, controller, task, on_step)


def _fly(sim: Simulator, controller, task: Task, on_step=None) -> Flight:
    sim.reset()
    # release the drone where its *measured* position (the mean of its IMUs) is task.start
    readings = sim.reset(position=task.start - sim.state(noisy=False).p)
    controller.reset(task)
    layout, tmax = sim.drone.layout, sim.drone.max_thrust
    flight = Flight(controller.name)
    steps = int(round(task.seconds / sim.cfg.control_dt))
    first = sim.state(noisy=False)
    flight.t.append(0.0)
    flight.x.append(first.x)
    flight.goal.append(task.goal(0.0).x)
    for k in range(steps):
        t = k * sim.cfg.control_dt
        try:
            u = np.asarray(controller.act(t, decompose(readings, layout)), dtype=float)
        except LqrFailure as err:
            flight.failure, flight.failure_time = f"controller: {err}", t
            break
        if not np.all(np.isfinite(u)):
            flight.failure, flight.failure_time = "controller: non-finite command", t
            break
        u = np.clip(u, -tmax, tmax)
        readings = sim.step(u)
        if not sim.alive:
            flight.failure, flight.failure_time = f"simulator: {sim.failure.reason}", sim.failure.time
            break
        flight.u.append(u)
        flight.t.append(sim.t)
        flight.x.append(sim.state(noisy=False).x)
        flight.goal.append(task.goal(sim.t).x)
        if on_step is not None:
            on_step()
    return flight


def metrics(flight: Flight, p_slice: slice, e_slice: slice, seconds: float) -> dict:
    a = flight.arrays()
    survival = flight.failure_time if flight.failure is not None else seconds
    p_err = np.linalg.norm(a["x"][:, p_slice] - a["goal"][:, p_slice], axis=1)
    tilt = np.abs(wrap_angle(a["x"][:, e_slice])).max() if len(a["x"]) else np.nan
    usage = float(np.abs(a["u"]).sum()) if len(a["u"]) else 0.0
    return {
        "survival_time": float(survival),
        "survived": flight.failure is None,
        "failure": flight.failure or "",
        "final_error": float(p_err[-1]),
        "mean_error_last_5s": float(p_err[a["t"] >= a["t"][-1] - 5.0].mean()),
        "thrust_usage": usage,
        "thrust_per_second": usage / max(survival, 1e-9),
        "max_attitude_deg": float(np.rad2deg(tilt)),
    }
