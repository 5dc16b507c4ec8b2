"""``SoftDroneEnv``: one soft drone and one task as a Gymnasium environment.

The step is the one ``sdexp.control.rollout.fly`` takes for the paper's controllers, so an agent
and ours (``sdexp.envs.policy.OursPolicy``) are compared on equal terms:

  observation  (x, x_goal) as float32: x = (s, s_dot, e, e_dot, p, p_dot), the decomposed state
               of the IMU readings (``sdexp.sensing.decompose``, with the configured sensor
               noise), and the task's goal state at the same time; never mesh internals. Bounded
               (``observation_bounds``) and clipped to the bounds: angles s, e in [-pi, pi] (they
               are wrapped); the position within the arena of the loss-of-control rule plus
               POSITION_SLACK (beyond it the episode has ended); the speed below what the full
               thrust reaches across that arena from rest; the bend and attitude rates within
               RATE_LIMIT, a bound the physics does not give (a soft body's vibration, a spin, and
               the Euler rates near 90 deg of pitch have none) and random thrusts did not come near
               (the rod and the flower tumbling with the tilt limit off: at most 26 rad/s);
  action       one number per rotor in [-1, 1] (``action_scale="normalized"``, the default, as
               Gymnasium and SB3 advise): thrust u = action * Tmax, Tmax = ``drone.max_thrust``
               (10 N per rotor by default; negative thrust reverses the rotor), or the thrusts in
               newtons, Box[-Tmax, Tmax] (``action_scale="newtons"``); beyond the box clipped. The
               simulator applies them after the configured output delay and rotor noise (noise:
               paper by default, ``noise.enabled=false`` off); one of another size, or not
               numbers, raises ``BadAction`` (a ValueError) naming it and the space;
  reward       exp(-c) in (0, 1] per control step, c = |p - p_goal|^2 / POSITION_SCALE^2 +
               |e - e_goal|^2 / ANGLE_SCALE^2 + |s - s_goal|^2 / ANGLE_SCALE^2 (noise-free state,
               angles wrapped): bounded and positive, so ending a flight early never pays;
  terminated   a simulator blow-up, a non-finite action, or the loss-of-control rule of every
               sdexp flight (``rollout.LossOfControl``, config ``flight``): tilt past 90 deg or
               10 m out of the arena; ``info["failure"]`` says which, as a flight's metrics do;
  truncated    after the task's duration (``task.seconds / sim.control_dt`` steps).

``reset(seed=...)`` seeds the sensor and rotor noise and the effects' random draws, so an episode
repeats exactly; ``reset()`` without a seed draws the next episode's seed from the env's
generator (one seeded reset fixes all that follow). ``render_mode="rgb_array"``: ``render()``
returns a picture of the deforming drone (sdexp.eval.animation.LivePicture), at ``render_fps``
= the control rate, so Gymnasium's RecordVideo plays episodes in real time.
"""
from __future__ import annotations

import reprlib

import gymnasium as gym
import numpy as np

from sdexp.control.rollout import LossOfControl, arena
from sdexp.control.tasks import Task, wrap_angle
from sdexp.errors import UserError
from sdexp.sensing import decompose

class BadAction(UserError, ValueError):
    """An action that is not in the env's action space: a ValueError, as Gymnasium's own checks
    raise, and a UserError, one line for sdexp's command line (sdexp.envs.bench)."""


POSITION_SCALE = 1.0    # m: an error of 1 m costs a factor e in the step's reward
ANGLE_SCALE = 0.5       # rad (29 deg), for the attitude and the bend angles alike

ACTION_SCALES = ("normalized", "newtons")
POSITION_SLACK = 1.0    # m past the arena in the position bounds: the step that leaves it, the sensor noise
NO_ARENA = 100.0        # m: the arena margin of the position bounds when flight.arena_margin is null
RATE_LIMIT = 100.0      # rad/s: the bend and attitude rates' bounds (16 turns a second)


class SoftDroneEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, drone: str = "rod", task: str = "hover", overrides=None, config=None,
                 action_scale: str = "normalized", render_mode: str | None = None, **task_kw):
        """``overrides``: Hydra overrides of the sdexp config (a list of ``key=value`` strings or
        a mapping), e.g. ``{"noise.enabled": False, "sim.element": "linear"}``; ``config``: an
        already composed typed config instead (``drone`` and ``overrides`` then unused).
        ``action_scale``: normalized (actions in [-1, 1], x Tmax) or newtons (the thrusts);
        ``render_mode``: None or rgb_array.
        ``task_kw``: the task's numbers (sdexp.envs.tasks.make_task: seconds, start, target,
        velocity; the deform task's angle_deg, settle_seconds, ramp_seconds, hold_seconds)."""
        from sdexp.envs.config import compose_config
        from sdexp.envs.tasks import make_task
        from sdexp.eval.run import compiling_said
        from sdexp.sim.drone import build_drone
        from sdexp.sim.simulator import Simulator

        # the keywords of the env itself first: a typo costs no meshing
        if action_scale not in ACTION_SCALES:
            raise UserError(f"action_scale = {action_scale!r} is unknown: choose one of {', '.join(ACTION_SCALES)}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise UserError(f"render_mode = {render_mode!r} is unknown: choose one of None, "
                            f"{', '.join(self.metadata['render_modes'])}")
        self.render_mode = render_mode
        compiling_said()   # a cold machine's first env takes a minute: the log says why
        self.cfg = config if config is not None else compose_config(drone, overrides)
        cfg = self.cfg
        self.drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
        layout = self.drone.layout
        self.task: Task = make_task(task, layout.dim, layout.n_s, **task_kw)
        self.task_name = task
        self.sim = Simulator(self.drone, cfg.sim, cfg.noise, seed=int(cfg.seed))
        self.limits = cfg.flight
        self.dt = float(cfg.sim.control_dt)
        self.max_steps = int(round(self.task.seconds / self.dt))
        self.max_thrust = float(self.drone.max_thrust)
        self.n = 2 * (layout.n_s + layout.n_e + layout.dim)
        # the blocks of x, in the order of State.x (sdexp.model.dynamics uses the same)
        sizes = {"s": layout.n_s, "s_dot": layout.n_s, "e": layout.n_e, "e_dot": layout.n_e,
                 "p": layout.dim, "p_dot": layout.dim}
        ends = np.cumsum([0, *sizes.values()])
        self.slices = {k: slice(int(a), int(b)) for k, a, b in zip(sizes, ends[:-1], ends[1:])}
        # thrust = action x action_scale: the agent's box is [-1, 1] or the thrusts' own
        self.action_scale = self.max_thrust if action_scale == "normalized" else 1.0
        high = np.float32(self.max_thrust / self.action_scale)
        self.action_space = gym.spaces.Box(-high, high, (self.drone.num_rotors,), np.float32)
        low, high = self.observation_bounds()
        self.observation_space = gym.spaces.Box(np.tile(low, 2), np.tile(high, 2), dtype=np.float32)
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.dt}   # RecordVideo: real time
        self._picture = None   # drawn on first render()
        self._lost = LossOfControl(self.task, self.limits)
        self._k = 0

    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the state half of the observation (the goal half has the same): the
        module's docstring says where each comes from."""
        sl, cfg = self.slices, self.cfg
        margin = NO_ARENA if self.limits.arena_margin is None else float(self.limits.arena_margin)
        lo, hi = arena(self.task)
        lo, hi = lo - margin - POSITION_SLACK, hi + margin + POSITION_SLACK
        # from rest, |v|^2 <= 2 a d: a the thrust's and gravity's most, d at most the box's diagonal
        accel = self.drone.num_rotors * self.max_thrust / float(cfg.drone.mass) + float(cfg.sim.gravity)
        speed = max(np.sqrt(2 * accel * float(np.linalg.norm(hi - lo))), float(np.abs(self.task.velocity).max()))
        high = np.empty(self.n)
        high[sl["s"]] = high[sl["e"]] = np.pi
        high[sl["s_dot"]] = high[sl["e_dot"]] = RATE_LIMIT
        high[sl["p_dot"]] = speed
        high[sl["p"]] = hi
        low = -high
        low[sl["p"]] = lo
        return low.astype(np.float32), high.astype(np.float32)

    # -------------------------------------------------------------------------------- the API
    def reset(self, *, seed: int | None = None, options=None):
        super().reset(seed=seed)
        episode_seed = int(self.np_random.integers(2 ** 63))
        sim = self.sim
        sim.rng = np.random.default_rng(episode_seed)
        sim.seed = episode_seed    # the effects' draws: seeded by (sim.seed, flight 0)
        sim.reset(flight=0)
        # released at rest where its *measured* position is the task's start, as fly() does
        readings = sim.reset(position=self.task.start - sim.state(noisy=False).p, flight=0)
        self._k = 0
        return self._observe(readings), self._info(None)

    def step(self, action):
        u = self._thrusts(action)
        failure = None
        if not np.all(np.isfinite(u)):
            failure = "controller: non-finite command"
            readings = self.sim.readings()
        else:
            readings = self.sim.step(np.clip(u, -self.max_thrust, self.max_thrust))
            if not self.sim.alive:
                failure = f"simulator: {self.sim.failure.reason}"
        self._k += 1
        state = self.sim.state(noisy=False)
        if failure is None:
            failure = self._lost.check(state)
        obs = self._observe(readings)
        reward = 0.0 if failure is not None and failure.startswith(("controller", "simulator")) \
            else self._reward(state.x)
        truncated = failure is None and self._k >= self.max_steps
        return obs, reward, failure is not None, truncated, self._info(failure, state.x)

    # -------------------------------------------------------------------------------- helpers
    def _thrusts(self, action) -> np.ndarray:
        """The action as the rotors' thrusts (x action_scale); one that is not numbers of the
        space's size is a BadAction naming it and the space (numpy's own error names neither). Any
        shape of that size is taken ((1, m) from a batch of one); a non-finite number ends the
        episode."""
        try:
            u = np.asarray(action)
            what = f"{type(action).__name__}, shape {u.shape}, dtype {u.dtype}"
        except ValueError:   # a ragged list
            u, what = None, f"{type(action).__name__} of ragged rows"
        shape = self.action_space.shape
        if u is None or u.dtype.kind not in "iuf" or u.size != int(np.prod(shape)):
            unit = "rotor thrusts (N)" if self.action_scale == 1.0 else \
                f"rotor thrusts as fractions of Tmax = {self.max_thrust:g} N"
            raise BadAction(f"action {reprlib.repr(action)} ({what}) is not in the action space {self.action_space}: "
                            f"expected {shape[0]} {unit}, a float array of shape {shape}")
        return u.astype(float).reshape(shape) * self.action_scale

    @property
    def t(self) -> float:
        return self.sim.t

    def goal(self) -> np.ndarray:
        return self.task.goal(self.sim.t).x

    def _observe(self, readings) -> np.ndarray:
        x = decompose(readings, self.drone.layout).x
        obs = np.concatenate([x, self.goal()]).astype(np.float32)
        space = self.observation_space
        return np.clip(obs, space.low, space.high)   # past the bounds the flight is over or lost

    def render(self) -> np.ndarray | None:
        """rgb_array: a (480, 640, 3) uint8 picture of the drone as it is now (None otherwise)."""
        if self.render_mode != "rgb_array":
            return None
        if self._picture is None:
            from sdexp.eval.animation import LivePicture
            name = self.spec.id if self.spec else self.drone.name
            self._picture = LivePicture(self.drone, f"{name}, {self.task_name}", list(self.cfg.sim.obstacles))
        return self._picture(np.asarray(self.sim.x, dtype=float), self.sim.t)

    def _error(self, x: np.ndarray) -> dict[str, np.ndarray]:
        g, sl = self.goal(), self.slices
        return {"p": x[sl["p"]] - g[sl["p"]], "e": wrap_angle(x[sl["e"]] - g[sl["e"]]),
                "s": wrap_angle(x[sl["s"]] - g[sl["s"]])}

    def _reward(self, x: np.ndarray) -> float:
        err = self._error(x)
        cost = (err["p"] @ err["p"]) / POSITION_SCALE ** 2 + (err["e"] @ err["e"] + err["s"] @ err["s"]) / ANGLE_SCALE ** 2
        return float(np.exp(-cost))

    def _info(self, failure: str | None, x: np.ndarray | None = None) -> dict:
        x = self.sim.state(noisy=False).x if x is None else x
        return {"t": float(self.sim.t), "failure": failure or "",
                "position_error": float(np.linalg.norm(self._error(x)["p"]))}
