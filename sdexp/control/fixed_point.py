"""A fixed point of the learned dynamics, f(x*, u*) = 0, found as the paper's ablation does: "by
trial-and-error and then fine-tune it with gradient descent using our learned networks".

Velocities are zero at a fixed point (the position rows of f are the velocities), so the search
is over the configuration (s, e) and the thrusts u, with p fixed (no network sees p):
  trial    ``trials`` random (s, u) pairs (s small, e = 0, u uniform in [0, Tmax]); keep the one
           of smallest |f|;
  descent  Adam on |f(x, u)|^2 over (s, e, u), u kept in [-Tmax, Tmax] by a tanh reparametrisation.
"""
from __future__ import annotations

import numpy as np
import torch

from sdexp.model.dynamics import LearnedDynamics


def find_fixed_point(dyn: LearnedDynamics, p: np.ndarray, max_thrust: float, seed: int = 0,
                     trials: int = 4096, steps: int = 2000, lr: float = 0.01) -> tuple[np.ndarray, np.ndarray, float]:
    """(x*, u*, |f(x*, u*)|)."""
    rng = np.random.default_rng(seed)
    sl = dyn.slices
    X = np.zeros((trials, dyn.n))
    X[:, sl["s"]] = rng.normal(0.0, 0.05, (trials, dyn.n_s))
    X[:, sl["p"]] = p
    U = rng.uniform(0.0, max_thrust, (trials, dyn.m))
    res = np.linalg.norm(dyn.f(X, U), axis=1)
    best = int(np.argmin(res))
    x = torch.as_tensor(X[best], dtype=dyn.dtype)
    free = torch.zeros(dyn.n, dtype=torch.bool)
    free[sl["s"]] = True
    free[sl["e"]] = True
    q = x[free].clone().requires_grad_(True)
    v = torch.atanh(torch.as_tensor(np.clip(U[best] / max_thrust, -0.999, 0.999), dtype=dyn.dtype)).requires_grad_(True)
    opt = torch.optim.Adam([q, v], lr=lr)
    for _ in range(steps):
        xx = x.clone()
        xx[free] = q
        loss = (dyn.f_torch(xx, max_thrust * torch.tanh(v)) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        x[free] = q
        u = max_thrust * torch.tanh(v)
    x, u = x.numpy().copy(), u.numpy().copy()
    return x, u, float(np.linalg.norm(dyn.f(x, u)))


def pollute(x: np.ndarray, u: np.ndarray, level: float, keep: slice, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray]:
    """x, u with every entry scaled by (1 + U[-level, level]) -- "uniform random noise proportional
    to each state variable" -- except x[keep] (the goal location stays untouched)."""
    xn = x * (1.0 + rng.uniform(-level, level, x.shape))
    xn[keep] = x[keep]
    return xn, u * (1.0 + rng.uniform(-level, level, u.shape))
