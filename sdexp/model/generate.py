"""Generation of training transitions (supplement F): one chunk of data, from sensor readings only.

A chunk is ``n`` consecutive transitions produced by episodes run one after another. Episode
``j`` of chunk ``c`` draws everything random (thrust holds and sensor/rotor noise) from
``SeedSequence(seed, spawn_key=(c, j))``, so a chunk is a pure function of the config, the seed,
its index and its length, whichever process runs it. A chunk of length ``n`` is a prefix of the
same chunk generated longer.

Every episode starts from ``Simulator.reset()`` (the undeformed drone at rest), every rotor holds
a thrust drawn from U[-Tmax, Tmax] for ``data.hold_seconds``, then a new draw (the paper's
recipe; ``data.thrust_range`` narrows the draw and ``data.around_hover`` centres it on a hover
thrust, the rest shape's minimum-norm one or, with ``data.hover: shape``, the one that holds
the body flattest; ``data.deform_range`` adds a thrust pattern held for
``data.deform_hold_seconds`` that puts no net lift or tilting torque on the rest shape, so that
the data visit held deformations in level flight). One transition per
control step: the state decomposed from the readings before the step, the command, and the
rates decomposed from the readings after it. An episode ends on a failure (the failing step is
dropped: its readings are frozen, not measured), after the step that takes p further than
``data.region`` from the start, after ``data.episode_seconds``, or at the end of the chunk.

The simulator always runs single-threaded here: the FEM force sum is not bitwise the same with
two threads, and the data must not depend on the number of worker processes.
"""
from __future__ import annotations

import json
import time
from collections import Counter
from typing import Callable, Iterator

from dataclasses import replace

import numba as nb
import numpy as np

from sdexp.cache import config_key
from sdexp.errors import UserError
from sdexp.sensing.rotations import euler_and_rates
from sdexp.sim.rigid.geometry import deformation_patterns, rest_hover_thrust
from sdexp.sensing import Readings, SensorLayout, State, decompose

# An episode that produces no transition (the drone fails in its first step from rest) this many
# times in a row means the drone cannot be simulated at all; stop instead of looping forever.
MAX_EMPTY_EPISODES = 20

# per-process simulator, reused across chunks: (config json, drone, simulator)
_CACHED: dict = {}


def widths(dim: int, n_s: int, m: int) -> dict[str, int]:
    """Per-transition width of every float array."""
    n_e = 3 if dim == 3 else 1
    n_raw = dim + n_e + n_s * n_e
    return {"s": n_s, "s_dot": n_s, "e": n_e, "e_dot": n_e, "p": dim, "p_dot": dim, "u": m,
            "s_dot_next": n_s, "e_dot_next": n_e, "p_dot_next": dim,
            "raw": n_raw, "raw_dot": n_raw, "raw_dot_next": n_raw}


def raw_state(r: Readings, st: State, layout: SensorLayout) -> tuple[np.ndarray, np.ndarray]:
    """The undecomposed state: (p, frame Euler angles, every peripheral IMU's world-frame Euler
    angles (2D: its angle)) and its rates. Angles are stored as read (yaw and 2D angles in
    (-pi, pi], not unwrapped); rates come from the gyroscopes by the chain rule
    (sdexp.sensing.rotations.euler_and_rates, compiled: 2 us instead of 35)."""
    pi = layout.periph_idx
    if layout.dim == 2:
        ang, rate = r.rot[pi], r.omega[pi]
    else:
        ang, rate = _euler_and_rates(r.rot, r.omega, pi)
    return (np.concatenate((st.p, st.e, ang.ravel())),
            np.concatenate((st.p_dot, st.e_dot, rate.ravel())))


@nb.njit(cache=True)
def _euler_and_rates(rot, omega, idx):
    """euler_and_rates of the IMUs idx, stacked."""
    n = len(idx)
    ang = np.empty((n, 3))
    rate = np.empty((n, 3))
    for k in range(n):
        ang[k], rate[k] = euler_and_rates(rot[idx[k]], omega[idx[k]])
    return ang, rate


def sim_config(spec: dict):
    """The simulator config of a data spec, single-threaded."""
    return replace(spec["sim"], threads=1)


def _simulator(spec: dict):
    """Build (or reuse, within this process) the drone and a single-threaded simulator."""
    from sdexp.sim.drone import build_drone
    from sdexp.sim.simulator import Simulator

    tag = json.dumps([config_key(spec["drone"]), config_key(spec["sim"]), config_key(spec["noise"]),
                      spec["cache_dir"]], sort_keys=True, default=str)
    if _CACHED.get("tag") != tag:
        sim_cfg = sim_config(spec)
        drone = build_drone(spec["drone"], spec["cache_dir"], sim_cfg.element)
        sim = Simulator(drone, sim_cfg, spec["noise"], 0)
        _CACHED.update(tag=tag, drone=drone, sim=sim)
    return _CACHED["drone"], _CACHED["sim"]


def _deformation(rng: np.random.Generator, patterns: np.ndarray, largest: float) -> np.ndarray:
    """A thrust offset in the span of ``patterns`` (geometry.deformation_patterns): an isotropic
    Gaussian projected on it (the same draw whichever basis spans it), its largest rotor offset
    drawn from U[0, largest]."""
    v = patterns @ (patterns.T @ rng.standard_normal(patterns.shape[0]))
    return rng.uniform(0.0, largest) * v / np.abs(v).max()


def thrust_draw(drone, data, sim_cfg, cache_dir=None) -> tuple[np.ndarray | float, np.ndarray | float]:
    """(centre, scale) of the data recipe's thrust draw, each per rotor or one for all: every hold
    draws ``centre + scale x U[lo, hi] x Tmax``. The centre is 0 (the paper's), or with
    ``around_hover`` the rest shape's hover thrust (``hover: rigid``) or the one that holds the
    body flattest (``hover: shape``, sim.rigid.statics.shape_hover_thrust: a few seconds of
    simulation). The scale is 1, or with ``bend_budget_deg`` each rotor's draw narrowed to the
    thrust that bends the body at most that much on its own (sim.rigid.statics.rotor_compliance
    at the centre): a soft arm is excited as far as a stiff one bends, not as far as the rotors
    reach (the octopus's arms bend 14.4 deg per N; with U[-3, 3] N the data's median bend is 32
    deg, with a 20 deg budget 15). Off by default: on the octopus, rod, leaf and orange peel it
    narrowed the data as meant and flew nothing more (docs/results.md, "The fleet")."""
    centre: np.ndarray | float = 0.0
    if data.around_hover:
        if data.hover == "shape":
            from sdexp.sim.rigid.statics import shape_hover_thrust
            centre = shape_hover_thrust(drone, sim_cfg, cache_dir=cache_dir)
        else:
            centre = rest_hover_thrust(drone, float(sim_cfg.gravity))
    if data.bend_budget_deg is None or drone.layout.n_s == 0:
        return centre, 1.0
    from sdexp.sim.rigid.statics import rotor_compliance
    reach = float(drone.max_thrust) * max(abs(f) for f in data.thrust_range)   # N: the widest draw
    compliance = rotor_compliance(drone, sim_cfg, np.broadcast_to(centre, (drone.num_rotors,)).astype(float))
    budget = np.radians(float(data.bend_budget_deg))
    return centre, np.minimum(1.0, budget / np.maximum(compliance * reach, 1e-12))


def commands(drone, data, draw: tuple[np.ndarray | float, np.ndarray | float], dt: float,
             rng: np.random.Generator) -> Iterator[np.ndarray]:
    """The data recipe's command at every control step of one episode (``data``: the data config;
    ``draw``: thrust_draw's (centre, scale)): per rotor ``centre`` + ``scale`` x U[lo, hi] x Tmax
    held ``hold_seconds``, plus a deformation pattern held ``deform_hold_seconds`` if
    ``deform_range`` > 0. Validates eagerly; yields forever."""
    centre, scale = draw
    tmax, m = drone.max_thrust, drone.num_rotors
    hold = max(1, int(round(data.hold_seconds / dt)))
    lo, hi = (tmax * f for f in data.thrust_range)
    deform = tmax * float(data.deform_range)
    patterns, deform_hold = None, 1
    if deform > 0:
        patterns = deformation_patterns(drone)
        if patterns.shape[1] == 0:
            raise UserError(f"data.deform_range = {data.deform_range}: drone {drone.name}'s "
                            f"{m} rotors have no thrust pattern free of net lift and tilting torque; set it to 0")
        deform_hold = max(1, int(round(data.deform_hold_seconds / dt)))

    def stream():
        offset, k = 0.0, 0
        while True:
            if deform > 0 and k % deform_hold == 0:
                offset = _deformation(rng, patterns, deform)
            if k % hold == 0:
                u = centre + offset + scale * rng.uniform(lo, hi, m)
            yield u
            k += 1
    return stream()


def generate_chunk(spec: dict, chunk: int, n: int,
                   progress: Callable[[int], None] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Transitions ``[chunk * chunk_samples, chunk * chunk_samples + n)`` of the dataset, as
    float32 arrays (``episode`` local to the chunk), and a summary of how the episodes ended."""
    t_start, cpu_start = time.perf_counter(), time.process_time()
    drone, sim = _simulator(spec)
    draw = spec["draw"] if "draw" in spec else thrust_draw(drone, spec["data"], sim_config(spec), spec["cache_dir"])
    data = spec["data"]
    dt = float(spec["sim"].control_dt)
    rows = Rows(n, widths(drone.layout.dim, drone.layout.n_s, drone.num_rotors), progress)
    ends: Counter = Counter()
    ep, empty = 0, 0
    while rows.i < n:
        ss_thrust, ss_noise = np.random.SeedSequence(spec["seed"], spawn_key=(chunk, ep)).spawn(2)
        cmds = commands(drone, data, draw, dt, np.random.default_rng(ss_thrust))
        sim.rng = np.random.default_rng(ss_noise)
        start = rows.i
        ends[episode(sim, drone.layout, lambda t, st: next(cmds), rows, ep, dt,
                     max(1, int(round(data.episode_seconds / dt))), float(data.region) ** 2)] += 1
        if rows.i == start:
            empty += 1
            if empty >= MAX_EMPTY_EPISODES:
                reason = sim.failure.reason if sim.failure else "unknown"
                raise UserError(f"drone {drone.name}: {empty} episodes in a row failed in their first "
                                f"step from rest ({reason}); check drone.* and sim.* (e.g. sim.substep)")
        else:
            empty = 0
        ep += 1
    arrays = rows.arrays()
    info = {"episodes": int(len(np.unique(arrays["episode"]))), "ends": dict(ends),
            "seconds": time.perf_counter() - t_start, "cpu_seconds": time.process_time() - cpu_start}
    return arrays, info


class Rows:
    """A chunk's transitions, filled row by row (float64 while filled, float32 when done), with
    progress reported every 200 rows."""

    def __init__(self, n: int, w: dict[str, int], progress: Callable[[int], None] | None):
        self.n, self.i, self.progress, self.reported = n, 0, progress, 0
        self.out = {k: np.empty((n, v)) for k, v in w.items()}
        self.episode, self.t = np.empty(n, dtype=np.int32), np.empty(n)

    def put(self, st, u, nxt, raw, raw_dot, raw_dot_next, ep: int, t: float) -> None:
        o, i = self.out, self.i
        o["s"][i], o["s_dot"][i], o["e"][i], o["e_dot"][i], o["p"][i], o["p_dot"][i] = \
            st.s, st.s_dot, st.e, st.e_dot, st.p, st.p_dot
        o["u"][i], o["s_dot_next"][i], o["e_dot_next"][i], o["p_dot_next"][i] = u, nxt.s_dot, nxt.e_dot, nxt.p_dot
        o["raw"][i], o["raw_dot"][i], o["raw_dot_next"][i] = raw, raw_dot, raw_dot_next
        self.episode[i], self.t[i] = ep, t
        self.i += 1
        if self.progress is not None and self.i - self.reported >= 200:
            self.progress(self.i - self.reported)
            self.reported = self.i

    def arrays(self) -> dict[str, np.ndarray]:
        if self.progress is not None and self.i > self.reported:
            self.progress(self.i - self.reported)
            self.reported = self.i
        arrays = {k: v.astype(np.float32) for k, v in self.out.items()}
        arrays["episode"] = self.episode
        arrays["t"] = self.t.astype(np.float32)
        return arrays


def episode(sim, layout, act: Callable[[float, State], np.ndarray], rows: Rows, ep: int, dt: float, ep_steps: int,
            region2: float) -> str:
    """One episode from rest into ``rows``, each command ``act(t, state read before the step)``
    (the random holds' next draw, or a controller's: sdexp.eval.aggregation), until the simulator
    fails (its reason), the drone leaves the region, the episode's time is up (timeout) or the
    chunk is full (chunk_end)."""
    r = sim.reset()
    st = decompose(r, layout)
    rw, rwd = raw_state(r, st, layout)
    p0 = st.p.copy()
    k = 0
    while True:
        u = act(k * dt, st)
        r = sim.step(u)
        if not sim.alive:
            return sim.failure.reason
        nxt = decompose(r, layout)
        rw1, rwd1 = raw_state(r, nxt, layout)
        rows.put(st, u, nxt, rw, rwd, rwd1, ep, k * dt)
        k += 1
        st, rw, rwd = nxt, rw1, rwd1
        d = st.p - p0
        if d @ d > region2:
            return "region"
        if k >= ep_steps:
            return "timeout"
        if rows.i >= rows.n:
            return "chunk_end"
