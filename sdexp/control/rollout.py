"""One flight loop for every controller and task, and the one metric computation they share.

``fly`` releases the drone at the task's start, then every control step: readings -> decomposed
state -> controller -> command clipped to [-Tmax, Tmax] -> simulator. The episode ends early on
  a simulator failure (blow-up): "simulator: <reason>";
  a controller failure (no stabilising Riccati solution, a non-finite command): "controller: ...";
  a loss of control, the same limits for every controller (config ``flight``, judged on the
  noise-free decomposed state recorded after each step): the body tilted more than
  ``max_tilt_deg`` from upright ("loss_of_control: tilt 93.2 deg > 90"), or the measured
  position farther than ``arena_margin`` from the box spanned by the task's start and its goal
  positions ("loss_of_control: left the arena, ...": ``arena``). The paper's survival time runs
  "before illegal configurations are encountered"; a flight that flips or flies off is one.
Each is recorded with its time, never raised. A loss-of-control step is recorded (the state that
crossed the limit is the flight's last); a blow-up step is not (its state is not sane).

Metrics (README "Metrics"):
  survival_time   s flown before the episode ended (the full duration if it did not);
  survived        no failure of any kind; ``failure`` its reason ("" if none);
  final_error     m, |p - p_goal| at the last recorded step (noise-free readings);
  thrust_usage    N, sum over control steps and rotors of |commanded thrust| (clipped), the
                  paper's "thrust usage"; ``thrust_per_second`` divides it by survival_time;
  max_tilt_deg    the largest tilt from upright (``tilt``), what the loss-of-control limit reads;
  max_attitude_deg  the largest |Euler angle| component (yaw included).

``recorder`` (a ``FrameRecorder``, off by default) keeps copies of the simulator's vertex
positions every few control steps for an animation (``sdexp.eval.animation``); it only reads
the simulator, so a flight's numbers are the same bit for bit with it or without it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from sdexp.control.controller import Controller
from sdexp.control.lqr import LqrFailure
from sdexp.config import FlightConfig
from sdexp.control.tasks import Task, wrap_angle
from sdexp.sensing import State, decompose
from sdexp.sensing.rotations import tilt_from_euler

if TYPE_CHECKING:   # the type only: fly calls the simulator it is handed (reset, step, state)
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


def tilt(e) -> np.ndarray:
    """Tilt from upright (rad, in [0, pi]) of the attitude block e (..., n_e) of the decomposed
    state: 2D |theta| (wrapped), 3D the angle between the body's up axis and world +Y
    (``rotations.tilt_from_euler``; no single Euler component measures it)."""
    e = np.asarray(e, dtype=float)
    return np.abs(wrap_angle(e[..., 0])) if e.shape[-1] == 1 else tilt_from_euler(e)


def arena(task: Task) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): the axis-aligned box spanned by the task's start and its goal positions over the
    task. The goal moves in a straight line (p_goal(t) = target + velocity t), so its positions at
    0 and task.seconds span them all. A flight is lost past ``arena_margin`` from this box."""
    pts = np.array([task.start, task.goal(0.0).p, task.goal(task.seconds).p])
    return pts.min(axis=0), pts.max(axis=0)


class LossOfControl:
    """The loss-of-control check of one flight: ``check(state)`` is None while the state is
    within the limits (config ``flight``), else the failure reason."""

    def __init__(self, task: Task, limits=None):
        limits = FlightConfig() if limits is None else limits
        self.max_tilt = None if limits.max_tilt_deg is None else float(limits.max_tilt_deg)
        self.margin = None if limits.arena_margin is None else float(limits.arena_margin)
        self.lo, self.hi = arena(task)

    def check(self, state: State) -> str | None:
        if self.max_tilt is not None:
            deg = float(np.rad2deg(tilt(state.e)))
            if deg > self.max_tilt:
                return f"loss_of_control: tilt {deg:.1f} deg > {self.max_tilt:g}"
        if self.margin is not None:
            out = np.maximum(0.0, np.maximum(self.lo - state.p, state.p - self.hi))
            d = float(np.linalg.norm(out))
            if d > self.margin:
                where = ", ".join(f"{v:.1f}" for v in state.p)
                return (f"loss_of_control: left the arena, {d:.2f} m > {self.margin:g} m from the box spanned "
                        f"by start and goal, at p = ({where})")
        return None


class FrameRecorder:
    """Copies of the simulator's vertex positions (the FEM nodes, (nv, dim)) at about ``fps``
    frames per simulated second: every ``every`` control steps, plus the release and the last
    recorded state of the flight. ``times`` (s) and ``points`` grow together."""

    def __init__(self, fps: float = 25.0):
        if not fps > 0:
            raise ValueError(f"fps = {fps!r}: allowed > 0")
        self.fps = float(fps)
        self.every, self.dt = 1, None
        self.times: list[float] = []
        self.points: list[np.ndarray] = []

    def start(self, sim: Simulator) -> None:
        self.dt = float(sim.cfg.control_dt)
        self.every = max(1, int(round(1.0 / (self.fps * self.dt))))
        self.times, self.points = [], []
        self._add(sim, sim.t)

    def step(self, sim: Simulator, done: int) -> None:
        """After ``done`` control steps."""
        if done % self.every == 0:
            self._add(sim, sim.t)

    def finish(self, sim: Simulator, t: float) -> None:
        """The flight's last recorded state (time ``t``), unless it is the last frame already
        (after a blow-up the simulator holds the last sane state, ``t`` its time)."""
        if not self.times or self.times[-1] != t:
            self._add(sim, t)

    def _add(self, sim: Simulator, t: float) -> None:
        self.times.append(float(t))
        self.points.append(np.array(sim.x, dtype=float, copy=True))

    @property
    def frame_rate(self) -> float:
        """Frames per simulated second actually recorded (the control rate over ``every``)."""
        return 1.0 / (self.every * self.dt) if self.dt else self.fps


def fly(sim: Simulator, controller: Controller, task: Task, on_step=None, limits=None, recorder=None) -> Flight:
    """``limits``: the loss-of-control limits (a ``FlightConfig`` or the ``flight`` config node);
    None = the schema's defaults. ``recorder``: a ``FrameRecorder`` to fill (None: nothing kept)."""
    # the controllers' matrices are tiny (28 x 28 at most): BLAS threads only add hand-offs and
    # stall when the simulator's threads hold the cores
    with threadpool_limits(1, user_api="blas"):
        return _fly(sim, controller, task, on_step, LossOfControl(task, limits), recorder)


def _fly(sim: Simulator, controller: Controller, task: Task, on_step, lost: LossOfControl, recorder=None) -> Flight:
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
    if recorder is not None:
        recorder.start(sim)
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
        state = sim.state(noisy=False)
        flight.u.append(u)
        flight.t.append(sim.t)
        flight.x.append(state.x)
        flight.goal.append(task.goal(sim.t).x)
        if on_step is not None:
            on_step()
        if recorder is not None:
            recorder.step(sim, k + 1)
        reason = lost.check(state)
        if reason is not None:
            flight.failure, flight.failure_time = reason, sim.t
            break
    if recorder is not None:
        recorder.finish(sim, flight.t[-1])
    return flight


def metrics(flight: Flight, p_slice: slice, e_slice: slice, seconds: float) -> dict:
    a = flight.arrays()
    survival = flight.failure_time if flight.failure is not None else seconds
    p_err = np.linalg.norm(a["x"][:, p_slice] - a["goal"][:, p_slice], axis=1)
    att = np.abs(wrap_angle(a["x"][:, e_slice])).max() if len(a["x"]) else np.nan
    up = tilt(a["x"][:, e_slice]).max() if len(a["x"]) else np.nan
    usage = float(np.abs(a["u"]).sum()) if len(a["u"]) else 0.0
    return {
        "survival_time": float(survival),
        "survived": flight.failure is None,
        "failure": flight.failure or "",
        "final_error": float(p_err[-1]),
        "mean_error_last_5s": float(p_err[a["t"] >= a["t"][-1] - 5.0].mean()),
        "thrust_usage": usage,
        "thrust_per_second": usage / max(survival, 1e-9),
        "max_tilt_deg": float(np.rad2deg(up)),
        "max_attitude_deg": float(np.rad2deg(att)),
    }
