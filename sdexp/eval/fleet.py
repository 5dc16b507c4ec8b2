"""``sdexp experiment=fleet``: ours across the paper's fleet (section 5: "We conduct training on
each model individually and use the generated controllers to direct the models to perform
hovering, target reaching, velocity tracking, and active deformation").

Every drone of ``experiment.params.drones`` (default: all twelve) and every seed of ``seeds`` is
one job: its own data (the drone's size by the data rule, ``samples``) and nets (cached, as in
every experiment), then each controller of ``controllers`` (ours and the rigid LQR) through
the four tasks with the paper's noise and 30 ms delay:

  hover     from release at rest, ``hover_seconds``;
  reach     a diagonal trip of ``reach_lengths`` body lengths (the drone's largest size);
  velocity  the goal moves along +x, its speed ramped from 0 to ``speed`` over ``ramp_seconds``,
            then held ``velocity_seconds``;
  deform    hover while the odd peripheral sensors (1, 3, ...) bend to the drone's target: settle,
            ramp, hold, ramp back to flat, hold. The paper states no amplitude; the rule: the bend
            the body's rotors reach open loop while it stays level (``statics.deform_reach``) times
            ``deform_reach_share``, at most ``deform_deg`` (``deform_target``). A target under the
            task's tolerance is not a task this body can be judged on: its rows say "beyond the
            body" with the reach, and nothing is flown.

Jobs run side by side (``workers`` processes, one core each); each writes ``jobs/<drone>_seed<k>.json``
when it ends, so an interrupted fleet resumes with the jobs it has (and the cached data and nets
of the rest). A job whose data or training fails is a recorded row with its reason; the fleet
goes on (a resumed run keeps that row: delete its job file to try the drone again). Per drone, once, the physics that decide whether it can fly at all (``physics_of``):
thrust-to-weight, the largest rotor's share of Tmax at hover, the fold that hover thrust holds
open loop, the rank of the rigid wrench, and how well its nets predict (beside the flights).

Every flight is said against its task's tolerance (``verdict``: within, missed by, lost control)
in the log, in ``fleet.csv``'s ``outcome`` column and in the summary.

Writes ``fleet.csv`` (one row per drone, seed, task and controller), ``physics.csv`` (one row
per drone and seed), ``fleet.png`` (drones x tasks per controller, colour = the task's error
against its tolerance, a cross for failures) and metrics with the fleet's wall time.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
import traceback
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp import conf
from sdexp.experiment_params import FleetParams
from sdexp.eval.run import Run

log = logging.getLogger(__name__)

# the error each task is judged by, and the error that reads "as far off as the task allows"
# (the figure's colour scale: 0 = perfect, 1 = at the tolerance):
#   hover, deform: the paper's hover band (5 cm) doubled for a release from rest;
#   reach: 10% of the trip (the paper's SOTA flower ends 2% off);
#   velocity: a quarter of the commanded speed.
PRIMARY = {"hover": "final_error", "reach": "final_error", "velocity": "velocity_error_rms",
           "deform": "bend_rms_deg"}
UNITS = {"final_error": "m", "velocity_error_rms": "m/s", "bend_rms_deg": "deg"}


def tolerance(task: str, p: FleetParams, trip: float) -> float:
    return {"hover": 0.1, "reach": 0.1 * trip, "velocity": 0.25 * float(p.speed), "deform": 5.0}[task]


# the designs the paper trains controllers for (supplement B: "For 2D drones, we only train
# controllers of the rod model"): its claim of breadth is about these seven
PAPER_DESIGNS = ("donut", "star", "flower", "leaf", "octopus", "orange_peel", "rod")

# a flight against its task's tolerance: it ended within it, survived but missed it, or failed;
# or a task the body cannot be judged on (the deform target under its tolerance), not flown
OUTCOMES = ("within", "missed", "lost control", "failed", "beyond the body")
BEYOND = "beyond the body"


def outcome(row: dict) -> str:
    """One of OUTCOMES: "failed" is a simulator blow-up or a controller failure, "lost control"
    the loss-of-control rule (tilt, arena); a survivor's error unmeasured counts as missed."""
    if str(row["failure"]).startswith(BEYOND):
        return BEYOND
    if not row["survived"]:
        return "lost control" if str(row["failure"]).startswith("loss_of_control") else "failed"
    return "within" if float(row["primary_value"]) <= float(row["tolerance"]) else "missed"


def verdict(row: dict) -> str:
    """A flight said against its tolerance: "within 0.1 m (0.059)", "missed by 2.64 m (2.74
    against 0.1)", "lost control at 1.20 s (tilt 93.1 deg)"."""
    from sdexp.eval.flights import short_reason
    kind = outcome(row)
    if kind == BEYOND:
        return str(row["failure"])
    if kind in ("lost control", "failed"):
        return f"{kind} at {row['survival_time']:.2f} s ({short_reason(row['failure'])})"
    value, tol, unit = float(row["primary_value"]), float(row["tolerance"]), UNITS[row["primary"]]
    if not np.isfinite(value):
        return f"missed: survived, its {row['primary']} not measured (tolerance {tol:.3g} {unit})"
    if kind == "within":
        return f"within {tol:.3g} {unit} ({value:.3g})"
    return f"missed by {value - tol:.3g} {unit} ({value:.3g} against {tol:.3g})"


def samples_for(p: FleetParams, n_s: int, dim: int, samples: int) -> int:
    """The data rule: ``samples_per_channel`` transitions per state channel (bends, attitude angles,
    position components), at least ``min_samples``, rounded up to whole hundreds; without a rule
    (null) ``samples`` (data.samples)."""
    if p.samples_per_channel is None:
        return int(samples)
    n_e = 3 if dim == 3 else 1
    n = max(int(p.min_samples), int(p.samples_per_channel) * (n_s + n_e + dim))
    return int(-(-n // 100) * 100)


def body_length(setup) -> float:
    """The drone's largest dimension (m): ``sim.drone.drone_length``."""
    from sdexp.sim.drone import drone_length
    return drone_length(setup.cfg.drone, setup.drone)


def deform_target(p: FleetParams, reach_deg: float) -> float:
    """The deform task's bend target (deg): ``deform_reach_share`` of the body's bend reach, at
    most ``deform_deg``."""
    return float(min(float(p.deform_deg), float(p.deform_reach_share) * float(reach_deg)))


def deform_schedule(n_s: int, p: FleetParams, target_deg: float) -> tuple[list, list, float]:
    """Keyframes (times, bend targets) of the deform task and its length: flat, the odd sensors
    up to ``target_deg``, held, flat again, held."""
    up = np.array([np.deg2rad(float(target_deg)) if i % 2 == 0 else 0.0 for i in range(n_s)])
    flat = np.zeros(n_s)
    t, ramp, hold = float(p.settle_seconds), float(p.deform_ramp_seconds), float(p.deform_hold_seconds)
    times, targets = [0.0, t], [flat, flat]
    for shape in (up, flat):
        times += [t + ramp, t + ramp + hold]
        targets += [shape, shape]
        t += ramp + hold
    return times, [list(x) for x in targets], t


def beyond_body(p: FleetParams, reach_deg: float) -> str:
    """Why the deform task is beyond a body whose bend reach is ``reach_deg`` (its target under the
    task's tolerance), or "" when it is not."""
    target, tol = deform_target(p, reach_deg), tolerance("deform", p, 0.0)
    if target >= tol:
        return ""
    return (f"{BEYOND}: its rotors bend it at most {reach_deg:.2g} deg while it stays level "
            f"(statics.deform_reach), the target {target:.2g} deg is under the {tol:g} deg tolerance")


def tasks_for(setup, p: FleetParams, reach_deg: float) -> dict:
    """name -> (Task, time from which its errors are measured); the deform task (its target from
    the body's bend reach ``reach_deg``) only where it is not beyond the body (``beyond_body``)."""
    dim, n_s = setup.layout.dim, setup.layout.n_s
    start = np.zeros(dim)
    out = {}
    for name in p.tasks:
        if name == "hover":
            out[name] = (setup.task(start, start, float(p.hover_seconds)), 0.0)
        elif name == "reach":
            trip = float(p.reach_lengths) * body_length(setup)
            out[name] = (setup.task(start, np.full(dim, trip / np.sqrt(dim)), float(p.reach_seconds)), 0.0)
        elif name == "velocity":
            v = np.zeros(dim)
            v[0] = float(p.speed)
            out[name] = (setup.task(start, start, float(p.ramp_seconds) + float(p.velocity_seconds), velocity=v,
                                    ramp=float(p.ramp_seconds)), float(p.ramp_seconds))
        elif not beyond_body(p, reach_deg):
            times, targets, seconds = deform_schedule(n_s, p, deform_target(p, reach_deg))
            out[name] = (setup.task(start, start, seconds, bend_times=times, bend_targets=targets),
                         float(p.settle_seconds))
    return out


def flight_errors(flight, dyn, since: float) -> dict:
    """Errors of a flight measured from ``since`` (s): velocity error RMS (m/s), bend tracking RMS
    (deg) and the largest position deviation from the goal (m)."""
    a = flight.arrays()
    sl = dyn.slices
    keep = a["t"] >= since
    if not keep.any():
        return {"velocity_error_rms": np.nan, "bend_rms_deg": np.nan, "max_position_deviation": np.nan}
    x, g = a["x"][keep], a["goal"][keep]
    dv = np.linalg.norm(x[:, sl["p_dot"]] - g[:, sl["p_dot"]], axis=1)
    ds = np.rad2deg(x[:, sl["s"]] - g[:, sl["s"]])
    dp = np.linalg.norm(x[:, sl["p"]] - g[:, sl["p"]], axis=1)
    return {"velocity_error_rms": float(np.sqrt(np.mean(dv ** 2))),
            "bend_rms_deg": float(np.sqrt(np.mean(ds ** 2))) if ds.size else 0.0,
            "max_position_deviation": float(dp.max())}


def physics_of(drone, sim_cfg, trained=None, hold_seconds: float = 2.0, cache_dir=None) -> dict:
    """Whether the body can fly at all, apart from any controller (``body_physics``), and the nets'
    validation error (mean absolute error of the predicted velocity change over that of copying
    the velocity: 1 = no better than "no change")."""
    out = body_physics(drone, sim_cfg, hold_seconds, cache_dir)
    if trained is not None:
        for name, h in trained.history.items():
            kept = h[h["selected"]] if "selected" in h and h["selected"].any() else h.tail(1)
            out[f"{name}_val_rel_l1"] = float(kept["val_rel_l1"].iloc[0])
    return out


BODY_PHYSICS_FORMAT = 1   # bump when body_physics (or what it calls) changes what it finds


def body_physics(drone, sim_cfg, hold_seconds: float = 2.0, cache_dir=None) -> dict:
    """Thrust-to-weight, the largest rotor's share of Tmax in the rest shape's minimum-norm hover
    thrust, the largest bend (deg) and the drop (m) after holding that thrust ``hold_seconds``
    open loop, noise-free, the rank of the rotors' wrench on lift and tilt (3 in 3D, 2 in 2D:
    what hovering level needs) and in all, the thrust patterns left to deform the body and the
    largest bend one of them holds while the body stays level (``statics.deform_reach``), the
    largest bend after holding instead the thrust that keeps the body flattest
    (``statics.shape_hover_thrust``: whether any thrust the rotors can give without lifting or
    tilting holds the body open), and the static hover of the deformed body with the design
    rule's verdict on it (``statics.static_hover``). With ``cache_dir`` found once per body and
    simulator config (every seed of a drone shares them; the octopus's take minutes)."""
    if cache_dir is None:
        return _body_physics(drone, sim_cfg, hold_seconds, None)
    from sdexp.cache import cached_arrays, content_digest, key_of
    key = key_of("bodyphysics", BODY_PHYSICS_FORMAT, {"body": content_digest(drone), "sim": content_digest(sim_cfg),
                                                      "seconds": hold_seconds})
    made = cached_arrays(cache_dir, key, lambda: {"json": np.array(json.dumps(
        _body_physics(drone, sim_cfg, hold_seconds, cache_dir)))})
    return json.loads(str(made["json"]))


def _body_physics(drone, sim_cfg, hold_seconds: float, cache_dir) -> dict:
    from sdexp.sim.rigid.geometry import deformation_patterns, rest_hover_thrust, rigid_body, wrench_matrix
    from sdexp.sim.rigid.statics import deform_reach, hold_state, static_hover

    fem, g, tmax = drone.fem, float(sim_cfg.gravity), float(drone.max_thrust)
    mass, _, _, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    W = wrench_matrix(pos, dirs)
    level = [1, 3, 5] if W.shape[0] == 6 else [1, 2]
    hover = rest_hover_thrust(drone, g)
    first, st, sane = hold_state(drone, sim_cfg, hover, hold_seconds)
    return {"mass_kg": float(mass), "rotors": int(len(hover)), "sensors": int(drone.layout.n_s),
            "thrust_to_weight": float(len(hover) * tmax / (mass * g)),
            "hover_thrust_max_share": float(np.abs(hover).max() / tmax),
            "hover_fold_deg": float(np.rad2deg(np.abs(st.s)).max()) if st.s.size else 0.0,
            "hover_drop_m": float(first.p[1] - st.p[1]),
            "hover_hold_blew_up": not sane,
            "lift_tilt_rank": int(np.linalg.matrix_rank(W[level])), "lift_tilt_needed": len(level),
            "wrench_rank": int(np.linalg.matrix_rank(W)), "deformation_patterns": int(deformation_patterns(drone).shape[1]),
            "deform_reach_deg": deform_reach(drone, sim_cfg, hold_seconds),
            **shape_hover_fold(drone, sim_cfg, hold_seconds, cache_dir),
            **static_hover(drone, sim_cfg, cache_dir=cache_dir).row()}


def shape_hover_fold(drone, sim_cfg, hold_seconds: float = 2.0, cache_dir=None) -> dict:
    """The largest bend (deg) after holding the shape-holding hover thrust ``hold_seconds`` open
    loop, noise-free, and whether the hold blew up: what is left of the fold when the rotors'
    thrust is spread to keep the body flat rather than evenly (the leaf: 63 deg evenly, 6 shaped)."""
    from sdexp.sim.rigid.statics import hold_state, shape_hover_thrust

    _, st, sane = hold_state(drone, sim_cfg, shape_hover_thrust(drone, sim_cfg, cache_dir=cache_dir), hold_seconds)
    return {"shape_hover_fold_deg": float(np.rad2deg(np.abs(st.s)).max()) if st.s.size else 0.0,
            "shape_hover_blew_up": not sane}


def model_at_hover(setup, steps: int = 10) -> dict:
    """What the learned model gets wrong after release under the rest shape's hover thrust: the
    mean over the first ``steps`` control steps of its predicted linear (m/s^2) and level angular
    (rad/s^2) accelerations along the true states, less the true ones (a noise-free simulation,
    the thrust acting at once). The truth is not zero: p is where the IMUs are, not the centre of
    mass, and an evenly spread thrust lifts light arms faster than a heavy middle (the octopus's p
    rises at 9.7 m/s^2 at release; its model says 6.4, and 0.5 three steps later where the truth
    is 8.2). The predictions themselves at release stay as ``model_accel_at_hover`` and
    ``model_tilt_accel_at_hover``. Then the model's
    thrust-to-angular-acceleration map against the rest shape's rigid body (Frobenius norm of the
    difference over the rigid map's): the truth only where the body hardly bends (a fold of a
    degree or less under hover thrust, ``physics_of``), a reference elsewhere."""
    from sdexp.sim.rigid.geometry import rest_hover_thrust, rigid_body
    from sdexp.sim.rigid.statics import hold_trace

    drone, dyn = setup.drone, setup.dyn
    fem = drone.fem
    mass, _, inertia, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    hover = rest_hover_thrust(drone, float(setup.cfg.sim.gravity))
    f, _, B = dyn.linearize(setup.simulator().state(noisy=False).x, hover)
    sl = dyn.slices
    dt = float(setup.cfg.sim.control_dt)
    states, _ = hold_trace(drone, setup.cfg.sim, hover, steps * dt)
    xs = [st.x for st in states]
    p_dot, e_dot = (np.arange(dyn.n)[sl[k]] for k in ("p_dot", "e_dot"))
    rates = np.concatenate([p_dot, e_dot])
    err = np.mean([dyn.f(x, hover)[rates] - (x_next - x)[rates] / dt for x, x_next in zip(xs[:-1], xs[1:])], axis=0)
    n_p = len(p_dot)
    if fem.dim == 3:
        rigid = np.linalg.solve(inertia, np.cross(pos, dirs).T)
        level = [0, 2]    # roll and pitch; yaw (e_y, about the up axis) has no truth to hold to
    else:
        rigid = ((pos[:, 0] * dirs[:, 1] - pos[:, 1] * dirs[:, 0]) / float(np.ravel(inertia)[0]))[None]
        level = [0]
    return {"model_accel_at_hover": float(np.linalg.norm(f[sl["p_dot"]])),
            "model_tilt_accel_at_hover": float(np.linalg.norm(f[sl["e_dot"]][level])),
            "model_accel_error_at_release": float(np.linalg.norm(err[:n_p])),
            "model_tilt_accel_error_at_release": float(np.linalg.norm(err[n_p:][level])),
            "model_torque_map_error": float(np.linalg.norm(B[sl["e_dot"]] - rigid) / np.linalg.norm(rigid)),
            **data_torque_map(setup.data.arrays, rigid, level, float(setup.cfg.sim.control_dt),
                              int(setup.cfg.model.command_delay))}


def data_torque_map(arrays: dict, rigid: np.ndarray, level: list[int], dt: float, delay: int,
                    max_tilt: float = 0.2) -> dict:
    """What the drone's own data say its thrust-to-angular-acceleration map is, by least squares
    on the transitions within ``max_tilt`` rad of level (angular acceleration on an intercept, the
    command, the rates, bends and angles), against the rest shape's rigid map: with the command
    sent at the transition (what the paper's nets learn from) and with the one acting on it,
    ``delay`` steps older (model.command_delay). ``ratio``: the fitted map's projection on the
    rigid one (1 = its size), ``error``: as model_torque_map_error."""
    from sdexp.model.training import acting_commands, horizon_rows

    acc = (arrays["e_dot_next"] - arrays["e_dot"]) / dt
    near = np.flatnonzero(np.abs(arrays["e"][:, level]).max(axis=1) < max_tilt)
    out = {}
    for label, d in (("sent", 0), ("acting", delay)):
        rows = np.intersect1d(near, horizon_rows(arrays, 1, d))
        u = acting_commands(arrays, d)[rows]
        X = np.c_[np.ones(len(rows)), u, *(arrays[k][rows] for k in ("e_dot", "s", "e"))].astype(np.float64)
        fit = np.linalg.lstsq(X, acc[rows], rcond=None)[0][1:1 + u.shape[1]].T
        out[f"data_torque_map_ratio_{label}"] = float(np.sum(fit * rigid) / np.sum(rigid * rigid))
        out[f"data_torque_map_error_{label}"] = float(np.linalg.norm(fit - rigid) / np.linalg.norm(rigid))
    out["data_level_transitions"] = int(len(near))
    return out


# ---------------------------------------------------------------------------------------- jobs

def job_config(cfg, name: str, seed: int, p: FleetParams):
    """The run's config for one drone and seed: its drone (the run's own, with its overrides, if it
    is that one), the data rule's samples, the drone's recipe (whose data.samples, if it sets them,
    win over the rule), and one core (jobs run side by side)."""
    drone = cfg.drone if name == cfg.drone.name else conf.drone(name)
    samples = samples_for(p, int(drone.num_sensors), int(drone.dim), int(cfg.data.samples))
    job = with_recipe(replace(cfg, drone=drone, seed=int(seed), data=replace(cfg.data, samples=int(samples))),
                      p.recipes.get(name), f"experiment.params.recipes.{name}")
    return replace(job, data=replace(job.data, workers=1), model=replace(job.model, threads=1),
                   sim=replace(job.sim, threads=1))


RECIPE_SECTIONS = ("data", "model", "control")   # the learning and control side, never the world


def with_recipe(cfg, recipe: dict | None, where: str):
    """``cfg`` with ``recipe``'s keys merged into its data, model and control sections
    (experiment.params.recipes: what one drone learns and flies with), checked as a whole config
    is: a section other than those, a key they lack, a value of the wrong type or out of range is
    a UserError naming ``where``."""
    if not recipe:
        return cfg
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from sdexp.config import check_schema, validate
    from sdexp.errors import UserError, one_line
    sections = {}
    for section, keys in recipe.items():
        if section not in RECIPE_SECTIONS:
            raise UserError(f"{where}.{section}: a recipe changes only {', '.join(RECIPE_SECTIONS)} "
                            "(the world and the tasks are the same for every drone's method)")
        own = getattr(cfg, section)
        if not isinstance(keys, dict):
            raise UserError(f"{where}.{section} = {keys!r}: allowed a mapping of {section} keys, "
                            f"e.g. {{{dataclasses.fields(own)[0].name}: ...}}")
        check_schema(keys, type(own), f"{where}.{section}.")
        try:
            sections[section] = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(own), keys))
        except OmegaConfBaseException as err:   # a value of the wrong type
            raise UserError(f"{where}.{section}: {one_line(err)}") from None
    out = replace(cfg, **sections)
    try:
        validate(out)
    except UserError as err:
        raise UserError(f"{where}: {err}") from None
    return out


def recipe_text(recipe: dict | None) -> str:
    """A recipe as the overrides that give it, e.g. ``model.linear=[d, g, h] model.command_delay=0``."""
    def flat(node, prefix):
        for key, value in node.items():
            if isinstance(value, dict):
                yield from flat(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}={'null' if value is None else value}".replace("'", "")
    return " ".join(flat(recipe or {}, ""))


def job_path(jobs_dir: Path, name: str, seed: int) -> Path:
    return jobs_dir / f"{name}_seed{seed}.json"


# FleetParams fields that do not change what one job flies (which jobs there are, how many run at
# once; the other drones' recipes)
NOT_JOB_PARAMS = ("drones", "seeds", "workers", "recipes")


def job_key(job_cfg, p: FleetParams) -> str:
    """What makes a job's result: its resolved config (the drone, its recipe, the world, the data,
    nets and controllers) and the tasks' params; the run folder, the cores and the cache do not."""
    from sdexp.cache import config_key, key_of
    job = {f.name: config_key(getattr(job_cfg, f.name)) for f in dataclasses.fields(job_cfg)
           if f.name not in ("cache_dir", "cores", "sweep_dir", "experiment")}
    params = {k: v for k, v in config_key(p).items() if k not in NOT_JOB_PARAMS}
    return key_of("fleet-job", 1, {"job": job, "params": params})


def done_job(path: Path, key: str, recipe: str) -> dict | None:
    """The result a finished job wrote for this ``key``, or None (not run, damaged, or made with
    another config: it is flown again). A result written before jobs were keyed (no ``key``) is
    taken when its recipe matches: those runs resumed only with the drones' configs unchanged."""
    try:
        done = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if "key" not in done:
        return done if done.get("recipe", "") == recipe else None
    return done if done["key"] == key else None


def write_job(path: Path, result: dict) -> None:
    """A job's result, written whole (a resumed fleet reads it back instead of flying again)."""
    from sdexp.files import atomic_write
    text = json.dumps(result, indent=1, default=float)
    atomic_write(path, lambda tmp: tmp.write_text(text))


def fly_job(cfg, name: str, seed: int, p: FleetParams, path: str, report=None) -> dict:
    """One drone and seed: learn, fly every task under every controller; written to ``path``.
    Never raises for the drone's sake: a failure is the job's ``error``, with its phase.
    ``report``: the phase it starts (a str, ``job_progress``), and 1 when it is done."""
    from sdexp.eval.controllers import LEARNED
    from sdexp.eval.flights import Setup

    def starting(what: str) -> str:
        if report is not None:
            report(f"{name} seed {seed}: {what}")
        return what

    job_cfg = job_config(cfg, name, seed, p)
    result = {"drone": name, "seed": int(seed), "key": job_key(job_cfg, p), "samples": int(job_cfg.data.samples),
              "recipe": recipe_text(p.recipes.get(name)), "rows": [],
              "physics": None, "error": None, "seconds": {}}
    phase, t0 = starting("learning (data and nets)"), time.perf_counter()
    # the learned model's columns where a controller flies on it (no data or nets otherwise)
    learned = any(c in LEARNED for c in p.controllers)
    try:
        setup = Setup(job_cfg, progress=False)
        if learned:
            setup.dyn   # identified here (Setup is lazy): the phase's seconds are the learning's
        result["seconds"]["learning"] = time.perf_counter() - t0
        phase = starting("physics")
        t1 = time.perf_counter()
        result["physics"] = {**physics_of(setup.drone, job_cfg.sim, setup.trained if learned else None,
                                          cache_dir=job_cfg.cache_dir), **(model_at_hover(setup) if learned else {})}
        if learned and setup.data.meta.get("joined"):   # data.aggregation: what each round added
            result["physics"].update(data_transitions=len(setup.data), data_rounds="; ".join(setup.data.meta["joined"]))
        result["seconds"]["physics"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        trip = float(p.reach_lengths) * body_length(setup)
        reach = result["physics"]["deform_reach_deg"]
        for task_name, (task, since) in tasks_for(setup, p, reach).items():
            for ctl_name in p.controllers:
                phase = starting(f"{task_name} under {ctl_name}")
                sim = setup.simulator()
                flight, m = setup.fly(sim, setup.controller(ctl_name, sim), task, f"{name} {task_name}")
                errors = flight_errors(flight, setup.layout, since)
                primary = PRIMARY[task_name]
                value = m[primary] if primary in m else errors[primary]
                result["rows"].append({
                    "drone": name, "seed": int(seed), "task": task_name, "controller": ctl_name,
                    "survived": bool(m["survived"]), "survival_time": m["survival_time"], "failure": m["failure"],
                    "seconds": task.seconds, "final_error": m["final_error"], **errors,
                    "max_tilt_deg": m["max_tilt_deg"], "thrust_usage": m["thrust_usage"],
                    "primary": primary, "primary_value": value, "tolerance": tolerance(task_name, p, trip),
                    **({"target_deg": deform_target(p, reach)} if task_name == "deform" else {})})
        beyond = beyond_body(p, reach) if "deform" in p.tasks else ""
        result["rows"] += [{"drone": name, "seed": int(seed), "task": "deform", "controller": ctl_name, "survived": False,
                            "survival_time": np.nan, "failure": beyond, "seconds": 0.0, "final_error": np.nan,
                            "primary": PRIMARY["deform"], "primary_value": np.nan, "tolerance": tolerance("deform", p, trip)}
                           for ctl_name in p.controllers if beyond]   # not flown: a row each, with the reason
        result["seconds"]["flights"] = time.perf_counter() - t1
    except Exception as err:   # the drone's failure is a finding, recorded; the fleet goes on
        result["error"] = f"{phase}: {type(err).__name__}: {err}".splitlines()[0][:500]
        result["traceback"] = traceback.format_exc()[-4000:]
    result["seconds"]["total"] = time.perf_counter() - t0
    write_job(Path(path), result)
    if report is not None:
        report(1)
    return result


def job_progress(bar):
    """The fleet's jobs' ``report``: a str is the phase a job starts, shown in the progress lines
    (a job learns for minutes), a number is jobs done."""
    def report(item) -> None:
        if isinstance(item, str):
            bar.set_postfix(now=item)
        else:
            bar.update(item)
    return report


def _order(names: list[str], seeds: list[int]) -> list[tuple[str, int]]:
    """Jobs, the costly ones first so that two workers end together: 3D drones before 2D ones
    (their simulation is 2-40x slower), each drone's seeds together (they share its mesh)."""
    dims = {n: int(conf.drone(n).dim) for n in names}
    return [(n, s) for n in sorted(names, key=lambda n: -dims[n]) for s in seeds]


def check(run: Run) -> None:
    """Every drone's recipe names a drone and, merged into its config, is within range, before
    anything is written."""
    from sdexp.errors import UserError
    drones = conf.names("drone")
    for name in run.params.recipes:
        if name not in drones:
            raise UserError(f"experiment.params.recipes.{name}: {name!r} is not a drone: allowed {', '.join(drones)}")
        job_config(run.cfg, name, 0, run.params)


def run(run: Run) -> dict:
    from sdexp.log import Phase
    from sdexp.parallel import run_spawned
    from sdexp.sim.drone import drone_names

    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    names = list(p.drones or drone_names())
    jobs_dir = out_dir / "jobs"
    jobs_dir.mkdir(exist_ok=True)
    todo, results, stale = [], {}, []
    for name, seed in _order(names, list(p.seeds)):
        path = job_path(jobs_dir, name, seed)
        done = done_job(path, job_key(job_config(cfg, name, seed, p), p), recipe_text(p.recipes.get(name)))
        if done is not None:
            results[(name, seed)] = done
        else:
            stale += [f"{name} seed {seed}"] if path.exists() else []
            todo.append((cfg, name, seed, p, str(path)))
    rule = ("data.samples" if p.samples_per_channel is None
            else f"{p.samples_per_channel} a state channel, at least {p.min_samples}")
    log.info(f"sdexp: fleet: {len(names)} drones x {len(p.seeds)} seeds; transitions ({rule}): " + ", ".join(
        f"{n} {job_config(cfg, n, 0, p).data.samples}" for n in names))
    if results:
        log.info(f"sdexp: fleet: resuming with {len(results)} of {len(results) + len(todo)} jobs done")
    if stale:
        log.info(f"sdexp: fleet: flown again, their results made with another config: {', '.join(stale)}")
    t0 = time.perf_counter()
    with Phase("fleet jobs (drone x seed)", total=len(todo), unit="jobs") as bar:
        workers = max(1, min(int(p.workers), len(todo)))
        if workers == 1:
            done = [fly_job(*job, report=job_progress(bar)) for job in todo]
        else:
            done = run_spawned(fly_job, todo, workers, job_progress(bar))
    for res in done:
        results[(res["drone"], res["seed"])] = res
    _fill_diagnostics(cfg, p, results, jobs_dir)
    calls = _invocations(out_dir, time.perf_counter() - t0, len(done))
    ordered = [results[(n, s)] for n in names for s in p.seeds]
    for res in ordered:
        if res["error"]:
            log.warning(f"sdexp: fleet: {res['drone']} seed {res['seed']} did not fly: {res['error']}")
        else:
            log.info(f"sdexp: fleet: {res['drone']} seed {res['seed']}: {res['samples']} transitions, job "
                     f"{res['seconds'].get('total', 0.0):.0f} s; " + "; ".join(
                         f"{r['task']} under {r['controller']} {verdict(r)}" for r in res["rows"]))
    table = fleet_table(ordered)
    physics = physics_table(ordered)
    run.table(table, "fleet")
    run.table(physics, "physics")
    fleet_plot(table, names, list(p.tasks), list(p.controllers), out_dir / "fleet.png", len(p.seeds))
    out = {"wall_seconds": float(sum(c["wall_seconds"] for c in calls)), "invocations": len(calls),
           "job_seconds": float(sum(r["seconds"].get("total", 0.0) for r in ordered)),
           "jobs": len(ordered), "jobs_run": len(done), "jobs_failed": sum(bool(r["error"]) for r in ordered)}
    for (drone, task, ctl), grp in table[table["task"] != "-"].groupby(["drone", "task", "controller"]):   # flown rows
        out[f"{drone}_{task}_{ctl}_survived"] = int(grp["survived"].sum())
        out[f"{drone}_{task}_{ctl}_within"] = int((grp["outcome"] == "within").sum())
        out[f"{drone}_{task}_{ctl}_beyond"] = int((grp["outcome"] == BEYOND).sum())
        if grp["primary_value"].notna().any():   # none where the task is beyond the body
            out[f"{drone}_{task}_{ctl}_{grp['primary'].iloc[0]}_median"] = float(grp["primary_value"].median())
    return out


def _invocations(out_dir: Path, wall: float, jobs_run: int) -> list[dict]:
    """The run's invocations so far, this one appended (``invocations.json``): a resumed fleet's
    wall time is the sum of its invocations', not the last one's."""
    from sdexp.files import atomic_write

    path = out_dir / "invocations.json"
    calls = json.loads(path.read_text()) if path.exists() else []
    calls.append({"wall_seconds": wall, "jobs_run": jobs_run})
    atomic_write(path, lambda tmp: tmp.write_text(json.dumps(calls, indent=1)))
    return calls


def _fill_diagnostics(cfg, p: FleetParams, results: dict, jobs_dir: Path) -> None:
    """Jobs written before a diagnostic joined the physics (``model_at_hover`` and its data fit,
    ``deform_reach_deg``, ``shape_hover_fold_deg``, the static hover; resumed runs) get it from their cached drone, data and nets, written back
    to the job's file; nothing is flown again."""
    from sdexp.eval.controllers import LEARNED
    from sdexp.eval.flights import Setup
    from sdexp.sim.rigid.statics import deform_reach, static_hover

    for (name, seed), res in results.items():
        phys = res["physics"]
        if phys is None or all(k in phys for k in ("model_accel_error_at_release", "deform_reach_deg",
                                                    "shape_hover_fold_deg", "design_rule")):
            continue
        setup = Setup(job_config(cfg, name, seed, p), progress=False)
        if "model_accel_error_at_release" not in phys and any(c in LEARNED for c in p.controllers):
            phys.update(model_at_hover(setup))
        if "deform_reach_deg" not in phys:
            phys["deform_reach_deg"] = deform_reach(setup.drone, setup.cfg.sim)
        if "shape_hover_fold_deg" not in phys:
            phys.update(shape_hover_fold(setup.drone, setup.cfg.sim, cache_dir=setup.cfg.cache_dir))
        if "design_rule" not in phys:
            phys.update(static_hover(setup.drone, setup.cfg.sim, cache_dir=setup.cfg.cache_dir).row())
        write_job(job_path(jobs_dir, name, seed), res)


FLIGHT_COLUMNS = ("drone", "seed", "task", "controller", "survived", "survival_time", "failure", "seconds",
                  "final_error", "velocity_error_rms", "bend_rms_deg", "max_position_deviation", "max_tilt_deg",
                  "thrust_usage", "primary", "primary_value", "tolerance", "outcome", "samples", "recipe")


def fleet_table(results: list[dict]) -> pd.DataFrame:
    """One row per drone, seed, task and controller; a job that did not fly is one row with its
    reason (task and controller '-')."""
    rows = []
    for res in results:
        if res["error"]:
            rows.append({"drone": res["drone"], "seed": res["seed"], "task": "-", "controller": "-",
                         "survived": False, "failure": f"job: {res['error']}", "samples": res["samples"],
                         "recipe": res.get("recipe", "")})
        for row in res["rows"]:   # the outcome from the row: a resumed fleet's older job files get it too
            rows.append({**row, "outcome": outcome(row), "samples": res["samples"], "recipe": res.get("recipe", "")})
    # every column a flight row has, also when no job flew (then all rows are failed jobs')
    return pd.DataFrame(rows).reindex(columns=list(dict.fromkeys([*FLIGHT_COLUMNS, *(k for r in rows for k in r)])))


def physics_table(results: list[dict]) -> pd.DataFrame:
    rows = [{"drone": r["drone"], "seed": r["seed"], "samples": r["samples"],
             **{f"{k}_seconds": v for k, v in r["seconds"].items()}, **(r["physics"] or {})} for r in results]
    return pd.DataFrame(rows)


def fleet_plot(table: pd.DataFrame, drones: list[str], tasks: list[str], controllers: list[str], path: Path,
               seeds: int) -> None:
    """Drones x tasks, one panel per controller: colour = the median error over the seeds that
    survived, against the task's tolerance (green 0, yellow at it, red at twice it); the text
    the median, the seeds within the tolerance and those that survived; a pair that flies (every
    seed within) framed in black; a grey cell with a cross = no seed survived."""
    from matplotlib.colors import LinearSegmentedColormap

    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    cmap = LinearSegmentedColormap.from_list("err", ["#1a9850", "#fee08b", "#d73027"])
    fig, axes = plt.subplots(1, len(controllers), figsize=(1.9 * len(tasks) * len(controllers) + 2.5,
                                                          0.45 * len(drones) + 1.8), squeeze=False)
    for ax, ctl in zip(axes[0], controllers):
        ax.set_xlim(0, len(tasks))
        ax.set_ylim(len(drones), 0)
        for i, drone in enumerate(drones):
            for j, task in enumerate(tasks):
                sel = table[(table["drone"] == drone) & (table["controller"] == ctl) & (table["task"] == task)] \
                    if len(table) and "task" in table else table.iloc[:0]
                ok = sel[sel["survived"].astype(bool)] if len(sel) else sel
                if len(sel) and (sel["outcome"] == BEYOND).all():
                    colour, text = "#f0f0f0", "beyond\nthe body"
                elif len(ok):
                    med = float(ok["primary_value"].median())
                    colour = cmap(min(med / float(ok["tolerance"].iloc[0]), 2.0) / 2.0)
                    within = int((sel["outcome"] == "within").sum())
                    text = f"{med:.2g} {UNITS[ok['primary'].iloc[0]]}\n{within}/{seeds} within, {len(ok)} up"
                else:
                    colour, text = "#bdbdbd", f"x\n0/{seeds}"
                flies = len(sel) == seeds and (sel["outcome"] == "within").all()
                ax.add_patch(plt.Rectangle((j, i), 1, 1, facecolor=colour, edgecolor="white", lw=2))
                if flies:   # inside the white grid lines
                    ax.add_patch(plt.Rectangle((j + 0.04, i + 0.06), 0.92, 0.88, fill=False, edgecolor="black", lw=1.5))
                ax.text(j + 0.5, i + 0.5, text, ha="center", va="center", fontsize=8,
                        fontweight="bold" if not len(ok) else "normal")
        ax.set_xticks(np.arange(len(tasks)) + 0.5)
        ax.set_xticklabels([f"{t}\n({PRIMARY[t].replace('_', ' ')})" for t in tasks], fontsize=8)
        ax.set_yticks(np.arange(len(drones)) + 0.5)
        ax.set_yticklabels(drones)
        ax.set_title(ctl)
        ax.tick_params(length=0)
        for s in ax.spines.values():
            s.set_visible(False)
    fig.suptitle(f"the fleet over {seeds} seeds: median error of the flights that survived "
                 "(green 0, yellow = the task's tolerance, red 2x), seeds within the tolerance and seeds up;\nframed: "
                 "flies (every seed within); grey x: none survived; beyond the body: a deform target under its "
                 "tolerance, not flown", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    save_figure(fig, path, dpi=110)


def summary(params: FleetParams, metrics: dict) -> str:
    """Per controller and task, the fleet's flights against the task's tolerance: within it,
    survived but missed it, lost (control lost or failed)."""
    flown = metrics["jobs"] - metrics["jobs_failed"]   # every job that flew flies every task
    lines = [f"  {metrics['jobs']} jobs (drone x seed), {metrics['jobs_failed']} did not fly; "
             f"wall {metrics['wall_seconds'] / 60:.1f} min"]
    for ctl in params.controllers:
        parts = []
        for task in params.tasks:
            count = {end: sum(v for k, v in metrics.items() if k.endswith(f"_{task}_{ctl}_{end}"))
                     for end in ("within", "survived", "beyond")}
            parts.append(f"{task} {count['within']} within, {count['survived'] - count['within']} missed, "
                         f"{flown - count['survived'] - count['beyond']} lost"
                         + (f", {count['beyond']} beyond the body" if count["beyond"] else ""))
        lines.append(f"  {ctl}, of {flown} flights a task against its tolerance: " + "; ".join(parts))
    return "\n".join(lines)
