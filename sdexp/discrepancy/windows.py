"""Prediction windows over a set of flights, and the simulator that predicts them.

A window starts at a measured row, is re-initialised there (sdexp.discrepancy.predict) and
predicts ``horizon`` control steps driven by the logged commands. Residuals are divided by
the noise floor sigma[k, c] (per horizon step and channel), so a nominal simulator on
nominal flights scores 1 per entry on average and every channel weighs by its own noise.

The start state is the measured row with its positions and angles (p, e, s) averaged, causally,
over the ``average`` rows up to it, each carried forward to the start by the trapezoid integral
of its measured rate. Why: a bend angle off by its noise (0.57 deg) re-initialises a bent shape
the body never had, and the vibration it sets off grows with the stiffness of the simulator
tested; on a stiffer-than-nominal flight that noise made the true stiffness predict worse than
the nominal one (README "Discrepancy workflow"). The rates (gyro, velocity) are not integrated
from anything and enter as measured.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sdexp.discrepancy.logs import angle_columns, channel_names
from sdexp.discrepancy.predict import BendMap, model_effects, predict_windows, residuals, wrap


@dataclass
class Windows:
    flights: list            # logs.Flight
    starts: list             # per flight: array of start rows
    horizon: int
    history: int
    channels: list[str]
    measured: np.ndarray     # (W, horizon, C)
    start_rows: np.ndarray   # (W, C) the (estimated) measured state each window starts from
    start_u: np.ndarray      # (W, m) the first command of each window
    flight_of: np.ndarray    # (W,) flight index
    stride: int = 0          # rows between a flight's window starts
    average: int = 1         # rows each start state is averaged over (start_estimate)

    @property
    def count(self) -> int:
        return len(self.flight_of)


def start_estimate(t: np.ndarray, y: np.ndarray, rows: np.ndarray, average: int, ang: np.ndarray) -> np.ndarray:
    """The channels at ``rows`` with the first half (p, e, s) the mean of the ``average`` rows
    up to each, carried forward by the integral of the second half (their rates)."""
    nq = y.shape[1] // 2
    rate = y[:, nq:]
    integral = np.concatenate([np.zeros((1, nq)),
                               np.cumsum(0.5 * np.diff(t)[:, None] * (rate[1:] + rate[:-1]), axis=0)])
    out = y[rows].copy()
    shift = np.zeros((len(rows), nq))
    for j in range(1, average):
        prev = np.maximum(rows - j, 0)
        d = y[prev, :nq] + integral[rows] - integral[prev] - y[rows, :nq]
        d[:, ang[:nq]] = wrap(d[:, ang[:nq]])
        shift += d
    out[:, :nq] += shift / max(average, 1)
    return out


def make_windows(flights, channels, horizon: int, stride: int, history: int, average: int = 1) -> Windows:
    starts = [np.arange(max(history, average - 1), len(f.t) - horizon, stride) for f in flights]
    return windows_at(flights, starts, channels, horizon, stride, history, average)


def preceding(w: Windows) -> Windows:
    """Each window's predecessor: the window of the same flight that ends where it starts (its
    start ``horizon`` rows earlier, at the flight's first row at the earliest: then it overlaps
    the window, which a causal user must skip; its command history may be shorter). What a
    causal estimate of a slowly varying input at a window's start is read from."""
    return windows_at(w.flights, [np.maximum(s - w.horizon, 0) for s in w.starts], w.channels, w.horizon,
                      w.stride, w.history, w.average)


def windows_at(flights, starts, channels, horizon: int, stride: int, history: int, average: int) -> Windows:
    """The windows of ``flights`` that start at rows ``starts`` (an array per flight)."""
    meas, rows, us, fl = [], [], [], []
    ang = angle_columns(channels)
    for i, (f, s) in enumerate(zip(flights, starts)):
        if len(s):
            idx = s[:, None] + 1 + np.arange(horizon)[None]
            meas.append(f.y[idx]); rows.append(start_estimate(f.t, f.y, s, average, ang))
            us.append(f.u[s]); fl.append(np.full(len(s), i))
    C = len(channels)
    cat = lambda a, shape: np.concatenate(a) if a else np.zeros(shape)
    return Windows(flights, list(starts), horizon, history, channels, cat(meas, (0, horizon, C)),
                   cat(rows, (0, C)), cat(us, (0, flights[0].u.shape[1] if flights else 0)),
                   cat(fl, (0,)).astype(int), stride, average)


def subset(w: Windows, flight_ids) -> Windows:
    """The windows of some flights only."""
    ids = list(flight_ids)
    keep = np.isin(w.flight_of, ids)
    remap = {f: k for k, f in enumerate(ids)}
    return replace(w, flights=[w.flights[f] for f in ids], starts=[w.starts[f] for f in ids],
                   measured=w.measured[keep], start_rows=w.start_rows[keep], start_u=w.start_u[keep],
                   flight_of=np.array([remap[f] for f in w.flight_of[keep]], dtype=int))


def thin(w: Windows, at_most: int) -> Windows:
    """At most ``at_most`` windows, evenly spread over the set (kept in flight order)."""
    if w.count <= at_most:
        return w
    keep = np.zeros(w.count, bool)
    keep[np.linspace(0, w.count - 1, at_most).round().astype(int)] = True
    starts, k = [], 0
    for s in w.starts:
        starts.append(s[keep[k:k + len(s)]])
        k += len(s)
    return replace(w, starts=starts, measured=w.measured[keep], start_rows=w.start_rows[keep],
                   start_u=w.start_u[keep], flight_of=w.flight_of[keep])


def prediction_model(noise_cfg) -> tuple:
    """(noise config, base effects) for predictions: no random noise, and the output delay,
    part of the nominal model, as an actuation_delay effect (the same whole-step FIFO when the
    delay is a multiple of the control step, with noise-free readings straight from step)."""
    n = noise_cfg
    base = [{"name": "actuation_delay", "delay": float(n.delay)}] if n.enabled and n.delay > 0 else []
    return replace(n, enabled=False), base


class Predictor:
    """Runs the simulator with given effects over a window set; counts its rollouts."""

    def __init__(self, drone, sim_cfg, noise_cfg, bend: BendMap, bend_for=None):
        # bend_for(entries) -> the bend map of a body changed by those model effects (None: the
        # nominal map for every simulator)
        self.drone, self.bend, self.bend_for = drone, bend, bend_for
        self.sim_cfg = replace(sim_cfg, effects=[])
        self.noise, delay = prediction_model(noise_cfg)
        # the nominal model: the configured effects (a previous fit, say) and the output delay
        self.base = delay + list(sim_cfg.effects or [])
        self.ang = angle_columns(channel_names(drone.dim, drone.layout.n_s))
        self.rollouts = 0

    def residual(self, w: Windows, effects, before=None) -> np.ndarray:
        """measured - predicted (W, horizon, C) with ``effects`` (entries or Effect objects) in
        the simulator; ``before(k)`` runs before window k of ``w`` (per-window parameters)."""
        from sdexp.sim.simulator import Simulator
        # random effects (gusts) at their expectation: no prediction knows a flight's draws
        entries = self.base + list(effects)
        sim = Simulator(self.drone, self.sim_cfg, self.noise, seed=0, effects=entries, draws=False)
        changed = model_effects(entries) if self.bend_for is not None else []
        bend = self.bend_for(changed) if changed else self.bend
        out = np.empty_like(w.measured)
        k = 0
        for f, s in zip(w.flights, w.starts):
            if len(s) == 0:
                continue
            hook = None if before is None else (lambda j, k=k: before(k + j))
            pred = predict_windows(sim, bend, f, s, w.start_rows[k:k + len(s)], w.horizon, w.history, hook)
            out[k:k + len(s)] = residuals(pred, f, s, w.horizon, self.ang)
            k += len(s)
        self.rollouts += 1
        return out
