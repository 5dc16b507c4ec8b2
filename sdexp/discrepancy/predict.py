"""Short-horizon predictions of the simulator from measured states.

The logs hold sensor channels only, so a measured state is turned back into a mesh state:
the rest mesh posed rigidly at (p, e) with the rigid velocity of (p_dot, e_dot), plus a bend
field linear in s (its rate left out: see pose). The linear map is calibrated once per drone
on a nominal, noise-free flight of the simulator itself (least squares of body-frame vertex
displacements on s), which is knowledge of the model, not of the logs. A simulator whose effects
change the body itself (a payload, a stiffness or damping change: ``modify_model``) gets a map
calibrated on that body (``model_effects``), so a window re-initialises near that simulator's own
shape under the measured bends rather than the nominal body's: on the converged flower a 0.25 kg
payload's own simulator replayed its logs at 9x the noise floor through the nominal map and at
1.2x through its own (docs/discrepancy_workflow.md). Two
correction passes then shift the inputs until the posed mesh, read through the sensor pipeline
of the simulator being tested (its sensor effects included), reproduces the measured channels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sdexp.cache import cached_arrays, key_of
from sdexp.discrepancy.logs import angle_columns, state_row
from sdexp.sensing.rotations import euler_rate_matrix, matrix_from_euler
from sdexp.sensing import decompose
from sdexp.sim.sensors import read_imus

BEND_FORMAT = 3   # 2: the configs' key fields (sdexp.cache.config_key); 3: rotor thrust over its disc


def rotation(e: np.ndarray, dim: int) -> np.ndarray:
    if dim == 3:
        return matrix_from_euler(e)
    c, s = np.cos(e[0]), np.sin(e[0])
    return np.array([[c, -s], [s, c]])


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass
class BendMap:
    """Body-frame vertex displacement = s @ A + c (A: (n_s, nv*dim))."""
    rest_local: np.ndarray   # (nv, dim) rest mesh relative to the rest IMU mean
    A: np.ndarray
    c: np.ndarray

    def local(self, s: np.ndarray) -> np.ndarray:
        return self.rest_local + (s @ self.A + self.c).reshape(self.rest_local.shape)


def model_effects(entries) -> list:
    """The entries (dicts or Effect objects) whose effect changes the body itself (overrides
    ``modify_model``): what the bend map must be calibrated with."""
    from sdexp.sim.physics.effects import build_effects, overrides
    return [e for e, built in zip(entries, build_effects(entries)) if overrides(built, "modify_model")]


def rest_local(drone) -> np.ndarray:
    rest = drone.fem.rest
    r = read_imus(0.0, rest, np.zeros_like(rest), drone.imus)
    return rest - r.pos.mean(axis=0)


def fit_bend_map(drone, snapshots_x, states, ridge: float = 1e-6) -> BendMap:
    """Least squares of body-frame displacements on s over (x, State) snapshots."""
    L0 = rest_local(drone)
    D, S = [], []
    for x, st in zip(snapshots_x, states):
        R = rotation(st.e, drone.dim)
        D.append(((x - st.p) @ R - L0).ravel())
        S.append(st.s)
    D, S = np.array(D), np.array(S)
    Sc = np.c_[S, np.ones(len(S))]
    coef = np.linalg.solve(Sc.T @ Sc + ridge * len(S) * np.eye(Sc.shape[1]), Sc.T @ D)
    return BendMap(L0, coef[:-1], coef[-1])


def calibrate_bend_map(drone, sim_cfg, cache_dir: str, cache_key: dict, seconds: float = 20.0,
                       seed: int = 12345, effects=()) -> BendMap:
    """Fly the noise-free simulator (pilot + every manoeuvre), nominal or with ``effects`` (those
    that change the body: ``model_effects``), and fit the bend map; cached under the drone and
    simulator configuration and the effects."""
    from sdexp.config import NoiseConfig
    from sdexp.discrepancy.record import MANOEUVRES, Pilot, plan_flight, start_pose
    from sdexp.sim.simulator import Simulator

    def make():
        sim = Simulator(drone, sim_cfg, NoiseConfig(enabled=False), seed=seed, effects=list(effects))
        dt = sim.cfg.control_dt
        pilot = Pilot(drone, sim.cfg.gravity, dt=dt)
        xs, sts = [], []
        rng = np.random.default_rng(seed)
        sim.reset(start_pose(drone, 2.5))
        home = sim.state(noisy=False).p
        segs = plan_flight(drone, rng, seconds, dt, MANOEUVRES, home, 0.0, 0.3)
        for s in segs:
            for k in range(s.steps):
                st = sim.state(noisy=False)
                if k % 2 == 0:
                    xs.append(sim.x.copy()); sts.append(st)
                sim.step(pilot.act(st, s.end, 0 * home) + s.excite[k])
                if not sim.alive:
                    break
        bm = fit_bend_map(drone, xs, sts)
        return {"rest_local": bm.rest_local, "A": bm.A, "c": bm.c}

    key = {**cache_key, "effects": [e if isinstance(e, dict) else repr(e) for e in effects]} if effects else cache_key
    arrays = cached_arrays(cache_dir, key_of("bendmap", BEND_FORMAT, key), make)
    return BendMap(arrays["rest_local"], arrays["A"], arrays["c"])


def pose(y: np.ndarray, bend: BendMap, dim: int, n_s: int):
    """(x, v, R) of the mesh for channel row y (logs.channel_names order)."""
    ne = 3 if dim == 3 else 1
    i = 0
    p = y[i:i + dim]; i += dim
    e = y[i:i + ne]; i += ne
    s = y[i:i + n_s]; i += n_s
    p_dot = y[i:i + dim]; i += dim
    e_dot = y[i:i + ne]; i += ne
    s_dot = y[i:i + n_s]
    R = rotation(e, dim)
    rel = bend.local(s) @ R.T
    x = p + rel
    if dim == 3:
        w = euler_rate_matrix(e) @ e_dot
        spin = np.cross(w, rel)
    else:
        spin = e_dot[0] * np.c_[-rel[:, 1], rel[:, 0]]
    # the bend's rate is left out: s_dot carries the patches' vibration, which the linear map
    # turns into vertex velocities far larger than the mesh's (measured: 25 m/s errors)
    v = p_dot + spin
    return x, v, R


def reinit_state(sim, y: np.ndarray, bend: BendMap, passes: int = 2):
    """The mesh state whose readings in ``sim`` (its sensor effects included) match y."""
    d = sim.drone
    ang = angle_columns_cached(d)
    target = y.copy()
    x, v, R = pose(target, bend, d.dim, d.layout.n_s)
    for _ in range(passes):
        sim.body.x[:] = x
        sim.body.v[:] = v
        got = state_row(sim.state(noisy=False))
        err = y - got
        err[ang] = wrap(err[ang])
        target = target + err
        x, v, R = pose(target, bend, d.dim, d.layout.n_s)
    return x, v, R


_ANG = {}


def angle_columns_cached(drone) -> np.ndarray:
    key = (drone.dim, drone.layout.n_s)
    if key not in _ANG:
        from sdexp.discrepancy.logs import channel_names
        _ANG[key] = angle_columns(channel_names(*key))
    return _ANG[key]


def predict_windows(sim, bend: BendMap, flight, starts, start_rows, horizon: int, history: int,
                    before=None) -> np.ndarray:
    """(W, horizon, C) predicted channels for windows starting at rows ``starts``: re-initialise
    at the measured state ``start_rows`` (W, C), replay the ``history`` commands before it
    through the actuation chain, then step with the logged commands. A window whose simulation
    fails keeps its last state. ``before(w)`` runs before window w (a per-window parameter)."""
    C = flight.y.shape[1]
    layout = sim.drone.layout
    out = np.empty((len(starts), horizon, C))
    for w, i0 in enumerate(starts):
        if before is not None:
            before(w)
        x, v, R = reinit_state(sim, start_rows[w], bend)
        sim.set_state(x, v, R, t=flight.t[i0], history=flight.u[max(0, i0 - history):i0])
        for k in range(horizon):
            # the simulator's noise is off here: step's readings are the noise-free ones
            out[w, k] = state_row(decompose(sim.step(flight.u[i0 + k]), layout))
    return out


def residuals(pred: np.ndarray, flight, starts, horizon: int, ang: np.ndarray) -> np.ndarray:
    """measured - predicted, (W, horizon, C), angle channels (mask ``ang``) wrapped."""
    idx = np.asarray(starts)[:, None] + 1 + np.arange(horizon)[None]
    r = flight.y[idx] - pred
    r[..., ang] = wrap(r[..., ang])
    return r
