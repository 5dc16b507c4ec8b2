"""ours (Algorithm 1, sdexp.control.relinearizing) as a policy that acts in a SoftDroneEnv from its
observations alone, so that an agent and the paper's controller are compared on equal terms.

It is identified from the env's config as every sdexp experiment identifies it (training data,
d, g, h: sdexp.model.identification, cached) and configured by its ``control`` group. Each step
it reads the decomposed state and the goal from the observation (never the simulator) and
returns the thrusts in the env's action space (fractions of Tmax by default). ``predict`` has
Stable-Baselines3's signature, so
``stable_baselines3.common.evaluation.evaluate_policy(OursPolicy(env), env)`` evaluates it like an
agent; a vectorised env gets one controller per sub-env.
"""
from __future__ import annotations

import numpy as np

from sdexp.control.lqr import LqrFailure
from sdexp.sensing import State


class _ObservedGoal:
    """The task as the controller sees it through the observation: the goal state of the last
    observation (sdexp.control.tasks.Task's ``goal(t)``)."""

    def __init__(self, slices: dict[str, slice]):
        self.slices = slices
        self.x = None

    def goal(self, t: float) -> State:
        return _state(self.x, self.slices)


def _state(x: np.ndarray, sl: dict[str, slice]) -> State:
    return State(*(x[sl[k]] for k in ("s", "e", "p", "s_dot", "e_dot", "p_dot")))


class OursPolicy:
    name = "ours"

    def __init__(self, env, progress: bool = True):
        """``env``: a SoftDroneEnv, as gymnasium.make returns it (wrappers are looked through) or a
        vector env's first sub-env; its config and observation layout are all this reads."""
        from sdexp.model.identification import identify

        base = getattr(env, "unwrapped", env)
        self.cfg, self.slices, self.n = base.cfg, base.slices, base.n
        self.dt, self.max_thrust, self.action_scale = base.dt, base.max_thrust, base.action_scale
        _, _, self.dyn = identify(self.cfg, progress)
        self._controllers: list = []

    def _controller(self):
        from sdexp.eval.controllers import ours
        c = ours(self.cfg, self.dyn, self.max_thrust)
        c.observed = _ObservedGoal(self.slices)
        return c

    def reset(self, count: int = 1) -> None:
        """A new episode in every one of ``count`` envs."""
        self._controllers = []
        for i in range(count):
            self._restart(i)

    def _restart(self, index: int) -> None:
        """A fresh episode for sub-env ``index`` (its controller made on first use)."""
        while len(self._controllers) <= index:
            self._controllers.append(self._controller())
        c = self._controllers[index]
        c.reset(c.observed)
        c.steps = 0

    def act(self, obs, index: int = 0) -> np.ndarray:
        """The action for one observation (of sub-env ``index``): the thrusts / action_scale."""
        if len(self._controllers) <= index:
            self._restart(index)
        c = self._controllers[index]
        obs = np.asarray(obs, dtype=float)
        c.observed.x = obs[self.n:]
        try:
            u = c.act(c.steps * self.dt, _state(obs[: self.n], self.slices))
        except LqrFailure:
            # no stabilising gain on the learned model at this state: as fly() records it, the
            # episode ends with a controller failure (the env terminates on a non-finite action)
            u = np.full(len(c.u), np.nan)
        c.steps += 1
        return (np.clip(u, -self.max_thrust, self.max_thrust) / self.action_scale).astype(np.float32)

    def __call__(self, obs) -> np.ndarray:
        return self.act(obs)

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """Stable-Baselines3's signature: (actions, None); ``episode_start`` (one flag per env)
        restarts that env's controller. One observation (obs_dim,) or a batch (n_envs, obs_dim)."""
        obs = np.asarray(observation, dtype=float)
        batch = obs.reshape(-1, obs.shape[-1])
        if episode_start is not None:
            for i in np.flatnonzero(np.asarray(episode_start, bool).reshape(-1)):
                self._restart(int(i))
        actions = np.stack([self.act(o, i) for i, o in enumerate(batch)])
        return (actions if obs.ndim > 1 else actions[0]), None
