"""The four task kinds of the paper (sdexp.control.tasks) as environment presets, in the
dimension of the drone; every number can be changed by a keyword of ``gymnasium.make``.

  hover     hold the release point, level, for ``seconds`` (10 s);
  reach     fly from the release point to ``target`` (the SOTA task: 3 m along every axis, 20 s);
  velocity  track a goal moving at ``velocity`` from the release point (the obstacle experiment's
            0.4, 0.2 (, 0) m/s, 15 s);
  deform    hover while raising alternate wings by ``angle_deg`` (hover_deform's schedule: settle
            2 s, then ramp 2 s and hold 3 s for odd wings up, even wings up, flat; 17 s).
"""
from __future__ import annotations

import numpy as np

from sdexp.control.tasks import Task
from sdexp.errors import UserError

TASKS = ("hover", "reach", "velocity", "deform")

DEFAULT_SECONDS = {"hover": 10.0, "reach": 20.0, "velocity": 15.0}
REACH_LEG = 3.0                           # m along every axis (the paper's (0,0,0) -> (3,3,3))
VELOCITY = {2: [0.4, 0.2], 3: [0.4, 0.2, 0.0]}
DEFORM = {"angle_deg": 15.0, "settle_seconds": 2.0, "ramp_seconds": 2.0, "hold_seconds": 3.0}


def make_task(kind: str, dim: int, n_s: int, seconds: float | None = None, start=None, target=None,
              velocity=None, **deform) -> Task:
    """The ``kind`` task for a drone of dimension ``dim`` with ``n_s`` bend angles; None keeps a
    preset. ``deform`` takes DEFORM's keys (deform task only)."""
    if kind not in TASKS:
        raise UserError(f"task = {kind!r} is unknown: choose one of {', '.join(TASKS)}")
    unknown = sorted(set(deform) - set(DEFORM))
    if unknown or (deform and kind != "deform"):
        allowed = "seconds, start, target, velocity" + (", " + ", ".join(DEFORM) if kind == "deform" else "")
        raise UserError(f"task keyword {(unknown or sorted(deform))[0]!r} does not apply to the {kind} task: "
                        f"allowed {allowed}")
    start = _vector("start", np.zeros(dim) if start is None else start, dim)
    goal = {"reach": start + REACH_LEG}.get(kind, start) if target is None else _vector("target", target, dim)
    vel = _vector("velocity", VELOCITY[dim] if kind == "velocity" and velocity is None else
                  (velocity if velocity is not None else np.zeros(dim)), dim)
    times, targets = [], []
    if kind == "deform":
        from sdexp.eval.hover_deform import schedule
        p = {**DEFORM, **deform}
        times, targets = schedule(n_s, np.deg2rad(float(p["angle_deg"])), float(p["settle_seconds"]),
                                  float(p["ramp_seconds"]), float(p["hold_seconds"]))
        seconds = times[-1] if seconds is None else seconds
    seconds = DEFAULT_SECONDS.get(kind) if seconds is None else float(seconds)
    if not (np.isfinite(seconds) and seconds > 0):
        raise UserError(f"seconds = {seconds!r} is out of range: allowed > 0")
    return Task(start=start, target=goal, seconds=seconds, n_s=n_s, velocity=vel,
                bend_times=times, bend_targets=targets)


def _vector(name: str, value, dim: int) -> np.ndarray:
    v = np.asarray(value, dtype=float).ravel()
    if v.shape != (dim,) or not np.all(np.isfinite(v)):
        raise UserError(f"{name} = {np.atleast_1d(value).tolist()!r}: allowed {dim} finite numbers (the drone is {dim}D)")
    return v
