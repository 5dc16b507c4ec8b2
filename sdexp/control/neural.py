"""The paper's third baseline: a neural controller trained end to end through the learned
dynamics used as a differentiable simulator (after Spielberg et al. 2019).

Policy: u = Tmax tanh(MLP(features)), features = (s, s_dot, wrap(e), e_dot, p - p_goal, p_dot),
so it is translation-invariant like the learned h (which does not see p).
Training: batches of initial states, half the rest state (the task's release condition) and half
states drawn from the training data, each with a goal offset drawn uniformly in a ball of radius
``goal_radius``; rolled out for ``horizon`` steps through x_{k+1} = x_k + dt f(x_k, u_k) (the
float32 learned d, g, h), loss = mean over steps of
    |p - p_goal|^2 / goal_radius^2 + w_att |e|^2 + w_bend |s|^2 + w_vel |p_dot|^2 + w_u |u / Tmax|^2,
back-propagated through the whole rollout (gradient norm clipped), Adam. The policy is cached
under a key over the networks' key, the policy config and the seed.
"""
from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np
import torch
from torch import nn

from sdexp.cache import atomic_write, build_lock, config_key, key_of
from sdexp.log import Phase
from sdexp.control.tasks import Task, wrap_angle
from sdexp.model.dynamics import LearnedDynamics
from sdexp.sensing import State

log = logging.getLogger(__name__)

POLICY_VERSION = 2   # 2: the key from the config's key fields (sdexp.cache.config_key)


class Policy(nn.Module):
    def __init__(self, n: int, m: int, hidden: int, layers: int, max_thrust: float,
                 p: tuple[int, int], e: tuple[int, int]):
        super().__init__()
        self.args = (n, m, hidden, layers, float(max_thrust), tuple(p), tuple(e))
        dims = [n] + [hidden] * layers
        mods = []
        for a, b in zip(dims[:-1], dims[1:]):
            mods += [nn.Linear(a, b), nn.Tanh()]
        self.body = nn.Sequential(*mods, nn.Linear(dims[-1], m))
        self.max_thrust, self.p, self.e = float(max_thrust), slice(*p), slice(*e)
        self.register_buffer("scale", torch.ones(n))

    def features(self, x: torch.Tensor, p_goal: torch.Tensor) -> torch.Tensor:
        f = x.clone()
        f[..., self.p] = x[..., self.p] - p_goal
        f[..., self.e] = torch.remainder(x[..., self.e] + np.pi, 2 * np.pi) - np.pi
        return f / self.scale

    def forward(self, x: torch.Tensor, p_goal: torch.Tensor) -> torch.Tensor:
        return self.max_thrust * torch.tanh(self.body(self.features(x, p_goal)))


def _float32_dynamics(dyn: LearnedDynamics) -> LearnedDynamics:
    d32 = copy.copy(dyn)
    d32.parts = [(b, copy.deepcopy(net).float(), idx, cols) for b, net, idx, cols in dyn.parts]
    d32.dtype = torch.float32
    return d32


def policy_key(nets_key: str, cfg, seed: int) -> str:
    """``cfg``: a sdexp.config.NeuralControllerConfig."""
    return key_of("policy", POLICY_VERSION, {"nets": nets_key, "seed": int(seed), "cfg": config_key(cfg)})


def train_policy(dyn: LearnedDynamics, data_x: np.ndarray, max_thrust: float, cfg, seed: int,
                 progress: bool = True) -> tuple[Policy, list[float]]:
    """Returns the policy and its loss per iteration. ``data_x``: (N, n) states from the data."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)   # 64 x 128 matrices: a second thread only waits (and stalls on a busy core)
    try:
        with Phase("training neural controller", total=int(cfg.iterations), unit="iterations",
                   enabled=progress) as bar:
            return _train_policy(dyn, data_x, max_thrust, cfg, seed, bar)
    finally:
        torch.set_num_threads(threads)


def _train_policy(dyn, data_x, max_thrust, cfg, seed, bar):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    d32 = _float32_dynamics(dyn)
    sl = dyn.slices
    policy = Policy(dyn.n, dyn.m, int(cfg.hidden), int(cfg.layers), max_thrust,
                    (sl["p"].start, sl["p"].stop), (sl["e"].start, sl["e"].stop))
    spread = data_x.std(axis=0)
    spread[sl["p"]] = cfg.goal_radius
    policy.scale.copy_(torch.as_tensor(np.maximum(spread, 1e-3), dtype=torch.float32))
    opt = torch.optim.Adam(policy.parameters(), lr=float(cfg.lr))
    B, H, rad = int(cfg.batch), int(cfg.horizon), float(cfg.goal_radius)
    dim = sl["p"].stop - sl["p"].start
    losses = []
    for _ in range(int(cfg.iterations)):
        x0 = np.zeros((B, dyn.n))
        half = B // 2
        x0[half:] = data_x[rng.integers(0, len(data_x), B - half)]
        x0[:, sl["p"]] = 0.0
        offset = rng.normal(size=(B, dim))
        offset *= (rad * rng.random((B, 1)) ** (1 / dim)) / np.linalg.norm(offset, axis=1, keepdims=True)
        x = torch.as_tensor(x0, dtype=torch.float32)
        goal = torch.as_tensor(offset, dtype=torch.float32)
        loss = 0.0
        for _ in range(H):
            u = policy(x, goal)
            x = x + d32.dt * d32.f_torch(x, u)
            e = torch.remainder(x[:, sl["e"]] + np.pi, 2 * np.pi) - np.pi
            loss = loss + (((x[:, sl["p"]] - goal) ** 2).sum(1) / rad ** 2
                           + cfg.w_att * (e ** 2).sum(1) + cfg.w_bend * (x[:, sl["s"]] ** 2).sum(1)
                           + cfg.w_vel * (x[:, sl["p_dot"]] ** 2).sum(1)
                           + cfg.w_u * ((u / max_thrust) ** 2).sum(1)).mean()
        loss = loss / H
        opt.zero_grad()
        if torch.isfinite(loss):
            loss.backward()
            nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
            opt.step()
        losses.append(float(loss.detach()))
        bar.set_postfix(loss=f"{losses[-1]:.3f}")
        bar.update()
    return policy.eval(), losses


def load_or_train_policy(dyn, data_x, max_thrust, cfg, seed, nets_key, cache_dir, progress=True):
    path = Path(cache_dir).expanduser() / f"{policy_key(nets_key, cfg, seed)}.pt"
    loaded = _load_policy(path)
    if loaded is not None:
        return loaded
    with build_lock(path):   # concurrent jobs that need this policy: one trains, the others wait
        loaded = _load_policy(path, quiet=True)
        if loaded is not None:
            return loaded
        policy, losses = train_policy(dyn, data_x, max_thrust, cfg, seed, progress)
        blob = {"args": policy.args, "state": policy.state_dict(), "losses": losses}
        atomic_write(path, lambda tmp: torch.save(blob, tmp))
    return policy, losses


def _load_policy(path: Path, quiet: bool = False):
    if not path.exists():
        return None
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
        policy = Policy(*blob["args"])
        policy.load_state_dict(blob["state"])
        return policy.eval(), blob["losses"]
    except Exception as err:
        if not quiet:
            log.warning(f"sdexp: cache entry {path.name} is unreadable ({type(err).__name__}), retraining")
        return None


class NeuralController:
    name = "neural"

    def __init__(self, policy: Policy):
        self.policy = policy

    def reset(self, task: Task) -> None:
        self.task = task

    @torch.no_grad()
    def act(self, t: float, state: State) -> np.ndarray:
        x = torch.as_tensor(state.x, dtype=torch.float32)
        goal = torch.as_tensor(self.task.goal(t).p, dtype=torch.float32)
        return self.policy(x, goal).numpy().astype(float)
