"""The learned dynamics of Eq. 4 and its linearisation, Eq. 5-6.

    x = (s, s_dot, e, e_dot, p, p_dot)          (sdexp.sim.sensors.State.x order)
    f(x, u) = (s_dot, (d(s, s_dot, u) - s_dot) / alpha,
               e_dot, (g(s, s_dot, e, e_dot, u) - e_dot) / alpha,
               p_dot, (h(s, s_dot, e, e_dot, p_dot, u) - p_dot) / alpha)

with alpha the control interval (the networks predict the velocity one frame later).
``jacobians(x, u) -> (A, B)`` are df/dx and df/du at (x, u): the networks' input Jacobians by one
batched reverse-mode pass each (torch autograd), assembled into the block structure of Eq. 6
(identity blocks set exactly; a block whose input does not feed a network is exactly zero).
``step(x, u) = x + alpha f(x, u)`` is one explicit Euler step: the next velocities are the
networks' predictions, positions advance with the current velocities. Everything runs in
float64 copies of the trained networks, and f/step take batches (..., n) / (..., m).
"""
from __future__ import annotations

import copy
from typing import Mapping, Sequence

import numpy as np
import torch

from sdexp.model.networks import ResidualMLP
from sdexp.model.training import DECOMPOSED, NetSpec

# which state block holds each network's target velocity
_TARGET_BLOCK = {"s_dot_next": "s_dot", "e_dot_next": "e_dot", "p_dot_next": "p_dot"}
_POSITION_OF = {"s_dot": "s", "e_dot": "e", "p_dot": "p"}


def state_sizes(data) -> dict[str, int]:
    """n_s, n_e, dim, m from a dataset's arrays."""
    a = data.arrays if hasattr(data, "arrays") else data
    width = lambda k: int(np.asarray(a[k]).reshape(len(a[k]), -1).shape[1])
    return {"n_s": width("s"), "n_e": width("e"), "dim": width("p"), "m": width("u")}


class _one_thread:
    """Run tiny per-state torch work on one intra-op thread: on these 8-row matrices a second
    thread only adds synchronisation (measured 2.3 ms per jacobians() on one thread, 3.6 ms on
    two, at twice the CPU)."""

    def __enter__(self):
        self.n = torch.get_num_threads()
        if self.n != 1:
            torch.set_num_threads(1)

    def __exit__(self, *exc):
        if self.n != 1:
            torch.set_num_threads(self.n)


class LearnedDynamics:
    def __init__(self, nets: Mapping[str, ResidualMLP], n_s: int, n_e: int, dim: int, m: int,
                 alpha: float = 0.01, specs: Sequence[NetSpec] = DECOMPOSED, dtype=torch.float64,
                 dt: float | None = None):
        """``alpha``: the time between a network's input and its target (model.horizon frames);
        ``dt``: one control interval (default alpha), the step of a simulated rollout."""
        self.n_s, self.n_e, self.dim, self.m, self.alpha = int(n_s), int(n_e), int(dim), int(m), float(alpha)
        self.dt = self.alpha if dt is None else float(dt)
        sizes = {"s": n_s, "s_dot": n_s, "e": n_e, "e_dot": n_e, "p": dim, "p_dot": dim}
        self.slices: dict[str, slice] = {}
        o = 0
        for k in ("s", "s_dot", "e", "e_dot", "p", "p_dot"):
            self.slices[k] = slice(o, o + sizes[k])
            o += sizes[k]
        self.n = o
        self.slices["u"] = slice(o, o + m)   # in z = concat(x, u)
        self.dtype = dtype
        self.parts = []   # (velocity block, network, input columns of z)
        for spec in specs:
            block = _TARGET_BLOCK[spec.target]
            width = sizes[block]
            if width == 0:
                continue  # no peripheral sensors: no d, the s blocks are empty
            if spec.name not in nets:
                raise KeyError(f"LearnedDynamics needs network {spec.name!r}")
            net = copy.deepcopy(nets[spec.name]).to(dtype).eval()
            for prm in net.parameters():
                prm.requires_grad_(False)
            cols = np.concatenate([np.arange(self.n + m)[self.slices[k]] for k in spec.inputs])
            if net.n_in != len(cols) or net.n_out != width:
                raise ValueError(f"network {spec.name!r} is {net.n_in} -> {net.n_out}, the state needs "
                                 f"{len(cols)} -> {width}")
            self.parts.append((block, net, torch.as_tensor(cols, dtype=torch.long), cols))

    @classmethod
    def from_trained(cls, trained, data, dt: float, horizon: int = 1) -> "LearnedDynamics":
        """From a :class:`~sdexp.model.training.TrainedNets` and the dataset it was trained on;
        ``dt`` the control interval, ``horizon`` the frames between a net's input and target."""
        return cls(trained.nets, **state_sizes(data), alpha=dt * horizon, specs=trained.specs, dt=dt)

    # ------------------------------------------------------------------------------ torch
    def net_outputs(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predicted next velocities per block, from z = concat(x, u) (..., n + m)."""
        return {block: net(z.index_select(-1, idx)) for block, net, idx, _ in self.parts}

    def f_torch(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        z = torch.cat([x, u], dim=-1)
        nxt = self.net_outputs(z)
        pieces = []
        for vel in ("s_dot", "e_dot", "p_dot"):
            v = x[..., self.slices[vel]]
            pieces.append(v)
            pieces.append((nxt[vel] - v) / self.alpha if vel in nxt else torch.zeros_like(v))
        return torch.cat(pieces, dim=-1)

    def _as(self, a) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=self.dtype)

    # ------------------------------------------------------------------------------ numpy
    def f(self, x, u) -> np.ndarray:
        """Eq. 4: x_dot for x (..., n) and u (..., m)."""
        with torch.no_grad(), _one_thread():
            return self.f_torch(self._as(x), self._as(u)).numpy()

    def step(self, x, u) -> np.ndarray:
        """One explicit step x + alpha f(x, u) (batched)."""
        x = np.asarray(x, dtype=np.float64)
        return x + self.alpha * self.f(x, u)

    def jacobians(self, x, u) -> tuple[np.ndarray, np.ndarray]:
        """(A, B) = (df/dx, df/du) at one (x, u), by autograd, in the block form of Eq. 6."""
        _, A, B = self.linearize(x, u)
        return A, B

    def linearize(self, x, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(f(x, u), A, B) from the same network passes (Eq. 5 needs all three)."""
        x, u = np.asarray(x, dtype=np.float64).ravel(), np.asarray(u, dtype=np.float64).ravel()
        n, m, a = self.n, self.m, self.alpha
        if len(x) != n or len(u) != m:
            raise ValueError(f"x must have {n} entries and u {m}, got {len(x)} and {len(u)}")
        J = np.zeros((n, n + m))
        f0 = np.zeros(n)
        sl = self.slices
        for vel, pos in _POSITION_OF.items():        # d(pos)/dt = vel: identity blocks
            rows, cols = np.arange(n)[sl[pos]], np.arange(n)[sl[vel]]
            J[rows, cols] = 1.0
            f0[rows] = x[cols]
        z = torch.as_tensor(np.concatenate([x, u]), dtype=self.dtype)
        ins, outs, eyes = [], [], []
        with _one_thread():
            for block, net, idx, cols in self.parts:
                k = net.n_out
                zi = z.index_select(0, idx).expand(k, -1).clone().requires_grad_(True)
                ins.append(zi)
                outs.append(net(zi))                     # k identical rows: one per output
                eyes.append(torch.eye(k, dtype=self.dtype))
            grads = torch.autograd.grad(outs, ins, eyes) if ins else ()   # one reverse pass for all
        for (block, net, idx, cols), y, g in zip(self.parts, outs, grads):
            rows = np.arange(n)[sl[block]]
            J[np.ix_(rows, cols)] = g.numpy() / a        # (1/alpha) d net / d inputs
            J[rows, rows] -= 1.0 / a                     # (1/alpha)(d net / d v - I)
            f0[rows] = (y[0].detach().numpy() - x[rows]) / a
        return f0, J[:, :n], J[:, n:]
