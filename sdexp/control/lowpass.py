"""A controller that reads the decomposed state through a first-order low-pass (our extension,
off by default: the paper's controllers read the state as decomposed).

Why: the IMUs sit on an elastic body, so what they read is the rigid motion plus the body's
vibration, and the frame IMU's gyroscope reads the vibration's rate, which grows with its
frequency. A gain on the measured attitude rate therefore also feeds the first elastic mode back
into the rotors, 30 ms late; where the mode is soft and close to the rotors that loop is unstable
(spillover). Measured on the rainbow (docs/results.md "The fleet"; free-free modes 1.9, 5.0,
10 Hz): a 1 N differential thrust tilts its frame IMU 0.17 deg within 30 ms while the body as a
whole has turned 0.02 deg, and ours -- with its learned model or with the exact rigid one -- and
the rigid LQR drive that mode into a saturated differential-thrust oscillation at about 7 Hz
that costs the lift (the rigid LQR drops 7.6 m in 3 s). Without the 30 ms output delay the same
gains hover. A 30 ms time constant (a corner at 5 Hz) holds the rigid LQR's hover within 6 cm.

Each channel of the state (bends, attitude, position and their rates) is filtered alike,
y <- y + a (x - y) with a = dt / (tau + dt) (backward Euler, unconditionally stable), started at the
first reading of a flight; angle differences are wrapped so that a yaw across +-pi does not sweep
the long way round.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from sdexp.control.controller import Controller
from sdexp.control.tasks import Task, wrap_angle
from sdexp.sensing import State

_ANGLES = ("s", "e")
_CHANNELS = ("s", "s_dot", "e", "e_dot", "p", "p_dot")


class LowPassed:
    """``controller`` fed the state low-passed with time constant ``tau`` (s) at control step ``dt``."""

    def __init__(self, controller: Controller, tau: float, dt: float):
        if not tau > 0 or not dt > 0:
            raise ValueError(f"tau = {tau!r}, dt = {dt!r}: allowed > 0")
        self.inner, self.tau, self.dt = controller, float(tau), float(dt)
        self.a = self.dt / (self.tau + self.dt)
        self.name = controller.name
        self._y: dict[str, np.ndarray] | None = None

    def reset(self, task: Task) -> None:
        self._y = None
        self.inner.reset(task)

    def filtered(self, state: State) -> State:
        if self._y is None:
            self._y = {k: np.array(getattr(state, k), dtype=float) for k in _CHANNELS}
        else:
            for k in _CHANNELS:
                d = getattr(state, k) - self._y[k]
                if k in _ANGLES:
                    d = wrap_angle(d)
                y = self._y[k] + self.a * d
                self._y[k] = wrap_angle(y) if k in _ANGLES else y
        return replace(state, **{k: v.copy() for k, v in self._y.items()})

    def act(self, t: float, state: State) -> np.ndarray:
        return self.inner.act(t, self.filtered(state))

    def __getattr__(self, key):
        # what experiments read of the controller they built (ours' timings, K, ...) is the inner one's
        if key == "inner":
            raise AttributeError(key)
        return getattr(self.inner, key)
