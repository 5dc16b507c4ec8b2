"""Tasks: what a controller is asked to do, as a goal state over time in the blocks of the
decomposed state (s, e, p and their rates; sdexp.sensing.State).

One :class:`Task` covers the paper's four kinds and their combinations:
  hover               target = start, no velocity;
  target reaching     target elsewhere;
  velocity tracking   ``velocity`` != 0: the goal position moves, p_goal(t) = target + v t, or
                      after a ramp of ``ramp`` seconds in which the goal velocity grows linearly
                      from 0 to v (a step in the goal velocity jerks a soft body);
  active deformation  ``bend``: a schedule of target bend angles s(t), linear between keyframes.
The attitude goal is level (e = 0) unless ``attitude`` gives one.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sdexp.sensing import State


def wrap_angle(a):
    """a mapped into (-pi, pi] (so an error of exactly +-pi keeps one sign)."""
    return np.pi - (np.pi - np.asarray(a)) % (2 * np.pi)


@dataclass
class Task:
    start: np.ndarray                        # (dim,) measured position p at release (at rest)
    target: np.ndarray                       # (dim,) goal position at t = 0
    seconds: float
    n_s: int
    velocity: np.ndarray | None = None       # (dim,) goal velocity
    bend_times: Sequence[float] = field(default_factory=list)       # keyframe times (s)
    bend_targets: Sequence[Sequence[float]] = field(default_factory=list)  # (k, n_s) in rad
    attitude: Sequence[float] | None = None  # goal Euler angles (rad); None = level
    ramp: float = 0.0                        # s over which the goal velocity grows from 0 to velocity

    def __post_init__(self):
        self.start = np.asarray(self.start, dtype=float)
        self.target = np.asarray(self.target, dtype=float)
        dim = len(self.start)
        self.velocity = np.zeros(dim) if self.velocity is None else np.asarray(self.velocity, dtype=float)
        bend = np.asarray(self.bend_targets, dtype=float)
        self._bend = bend.reshape(-1, self.n_s) if self.n_s else bend.reshape(len(bend), 0)
        if len(self._bend) != len(self.bend_times):
            raise ValueError("bend_times and bend_targets need one keyframe each")
        if not self.ramp >= 0:
            raise ValueError(f"ramp = {self.ramp!r}: allowed >= 0")

    @property
    def dim(self) -> int:
        return len(self.start)

    def bend(self, t: float) -> np.ndarray:
        if not len(self._bend):
            return np.zeros(self.n_s)
        return np.array([np.interp(t, self.bend_times, col) for col in self._bend.T])

    def travelled(self, t: float) -> tuple[float, float]:
        """(distance, speed) of the goal along ``velocity`` at time t, as multiples of |velocity|
        seconds and of |velocity|: t and 1 without a ramp; t^2 / (2 ramp) and t / ramp on it."""
        if t >= self.ramp:
            return t - 0.5 * self.ramp, 1.0
        return 0.5 * t * t / self.ramp, t / self.ramp

    def goal(self, t: float) -> State:
        ne = 3 if self.dim == 3 else 1
        e = np.zeros(ne) if self.attitude is None else np.asarray(self.attitude, dtype=float)
        dist, speed = self.travelled(t)
        return State(s=self.bend(t), e=e, p=self.target + self.velocity * dist,
                     s_dot=np.zeros(self.n_s), e_dot=np.zeros(ne), p_dot=self.velocity * speed)
