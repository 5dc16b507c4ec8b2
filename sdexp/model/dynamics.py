"""The learned dynamics of Eq. 4 and its linearisation, Eq. 5-6.

    x = (s, s_dot, e, e_dot, p, p_dot)          (sdexp.sensing.State.x order)
    f(x, u) = (s_dot, (d(s, s_dot, u) - s_dot) / alpha,
               e_dot, (g(s, s_dot, e, e_dot, u) - e_dot) / alpha,
               p_dot, (h(s, s_dot, e, e_dot, p_dot, u) - p_dot) / alpha)

with alpha the control interval (the networks predict the velocity one frame later).
``jacobians(x, u) -> (A, B)`` are df/dx and df/du at (x, u): the networks' exact input
Jacobians by reverse-mode differentiation, assembled into the block structure of Eq. 6 (identity
blocks set exactly; a block whose input does not feed a network is exactly zero). The reverse
pass is written out in NumPy (``_MlpJacobian``, tested equal to torch.autograd to 1e-10): at one
sample torch's per-operation overhead made autograd ~4 ms of the relinearisation.
A rollout steps x + dt f(x, u) with ``dt`` the control interval (``alpha`` is the networks'
input-to-target time). Everything runs in float64 copies of the trained networks, and f takes
batches (..., n) / (..., m).
"""
from __future__ import annotations

import copy
from typing import Mapping, Sequence

import numpy as np
import torch

from sdexp.model.heading import TILT, YAW, applies, rotation, turn
from sdexp.model.networks import EnsembleMLP, ResidualMLP
from sdexp.model.specs import DECOMPOSED, NetSpec

# which state block holds each network's target velocity
_TARGET_BLOCK = {"s_dot_next": "s_dot", "e_dot_next": "e_dot", "p_dot_next": "p_dot"}
_POSITION_OF = {"s_dot": "s", "e_dot": "e", "p_dot": "p"}


class _MlpJacobian:
    """A ResidualMLP's value and input Jacobian at one point, by hand in float64 NumPy: the
    forward pass keeps the ReLU masks, the reverse pass multiplies the (n_out x hidden) row block
    back through the layers. At one sample torch autograd's per-operation overhead dominates; this
    took the flower's d, g, h Jacobians from 3.2-4.9 ms to 1.2-1.7 ms (bench_control)."""

    def __init__(self, net: ResidualMLP):
        g = lambda t: t.detach().double().numpy().copy()
        self.W_in, self.b_in = (g(net.inp.weight), g(net.inp.bias)) if net.inp is not None else (None, None)
        self.blocks = [(g(b.fc1.weight), g(b.fc1.bias), g(b.fc2.weight), g(b.fc2.bias)) for b in net.blocks]
        self.W_out, self.b_out = g(net.out.weight), g(net.out.bias)
        self.in_mean, self.in_std = g(net.in_mean), g(net.in_std)
        self.out_mean, self.out_std = g(net.out_mean), g(net.out_std)
        self.base = net.base.numpy().copy() if net.has_base else None
        self.prior = (g(net.prior_W), g(net.prior_b)) if getattr(net, "has_prior", False) else None

    def __call__(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(y, dy/dz) for one input z (n_in,)."""
        zs = (z - self.in_mean) / self.in_std
        if self.W_in is None:   # a linear net (hidden = 0)
            y = self.out_mean + self.out_std * (self.W_out @ zs + self.b_out)
            return self._add_base(z, y, (self.out_std[:, None] * self.W_out) / self.in_std)
        a = self.W_in @ zs + self.b_in
        mask0 = a > 0
        h = a * mask0
        masks = []
        for W1, b1, W2, b2 in self.blocks:
            c = W1 @ h + b1
            inner = c > 0
            s = h + W2 @ (c * inner) + b2
            outer = s > 0
            masks.append((inner, outer))
            h = s * outer
        y = self.out_mean + self.out_std * (self.W_out @ h + self.b_out)
        G = self.out_std[:, None] * self.W_out                # dy/dh of the last block's output
        for (W1, _, W2, _), (inner, outer) in zip(reversed(self.blocks), reversed(masks)):
            G = G * outer                                      # through the block's ReLU
            G = G + ((G @ W2) * inner) @ W1                    # skip + inner path
        return self._add_base(z, y, ((G * mask0) @ self.W_in) / self.in_std)

    def _add_base(self, z, y, J):
        if self.base is not None:
            y = y + z[self.base]
            J[np.arange(len(self.base)), self.base] += 1.0
        if self.prior is not None:
            y = y + self.prior[0] @ z + self.prior[1]
            J = J + self.prior[0]
        return y, J


class _MeanJacobian:
    """An EnsembleMLP's value and input Jacobian: the mean of its members'."""

    def __init__(self, net: EnsembleMLP):
        self.members = [_MlpJacobian(m) for m in net.members]

    def __call__(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ys, Js = zip(*(jac(z) for jac in self.members))
        return np.mean(ys, axis=0), np.mean(Js, axis=0)


def _jacobian(net):
    return _MeanJacobian(net) if isinstance(net, EnsembleMLP) else _MlpJacobian(net)


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


def state_slices(n_s: int, n_e: int, dim: int, m: int) -> dict[str, slice]:
    """Where each block of the decomposed state x = (s, s_dot, e, e_dot, p, p_dot) sits, and the
    command's in z = concat(x, u)."""
    sizes = {"s": n_s, "s_dot": n_s, "e": n_e, "e_dot": n_e, "p": dim, "p_dot": dim, "u": m}
    out, o = {}, 0
    for k, n in sizes.items():
        out[k] = slice(o, o + n)
        o += n
    return out


class LearnedDynamics:
    def __init__(self, nets: Mapping[str, ResidualMLP | EnsembleMLP], n_s: int, n_e: int, dim: int, m: int,
                 alpha: float = 0.01, specs: Sequence[NetSpec] = DECOMPOSED, dtype=torch.float64,
                 dt: float | None = None, delay: int = 0, bend_spread=None, frame: str = "world"):
        """``alpha``: the time between a network's input and its target (model.horizon frames);
        ``dt``: one control interval (default alpha), the step of a simulated rollout; ``delay``:
        control steps from a command to the thrust it sets (model.command_delay): u in f(x, u) is
        the command acting now, the one sent ``delay`` steps ago; ``bend_spread``: the standard
        deviation of each bend channel s in the data the nets learned from (None: not known), what
        tells a controller which bends the model saw move above the sensors' noise; ``frame``:
        "heading" for nets trained in the heading frame (model.frame, sdexp.model.heading)."""
        self.n_s, self.n_e, self.dim, self.m, self.alpha = int(n_s), int(n_e), int(dim), int(m), float(alpha)
        self.dt = self.alpha if dt is None else float(dt)
        self.delay = int(delay)
        self.bend_spread = None if bend_spread is None else np.asarray(bend_spread, dtype=float)
        sizes = {"s": n_s, "s_dot": n_s, "e": n_e, "e_dot": n_e, "p": dim, "p_dot": dim}
        self.slices = state_slices(n_s, n_e, dim, m)
        self.n = self.slices["u"].start
        self.dtype = dtype
        heading = applies(frame, self.n_e)
        cols_of = dict(self.slices)
        if heading:   # the nets read the tilt alone: e without its yaw
            cols_of["e"] = self.slices["e"].start + np.array(TILT)
        self.parts = []   # (velocity block, network, input columns of z)
        self.turned = []  # per part: where its input p_dot sits (heading frame), or None
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
            cols = np.concatenate([np.arange(self.n + m)[cols_of[k]] for k in spec.inputs])
            if net.n_in != len(cols) or net.n_out != width:
                raise ValueError(f"network {spec.name!r} is {net.n_in} -> {net.n_out}, the state needs "
                                 f"{len(cols)} -> {width}")
            self.parts.append((block, net, torch.as_tensor(cols, dtype=torch.long), cols))
            turned = heading and "e" in spec.inputs and block == "p_dot"
            p_dot = np.arange(self.n)[self.slices["p_dot"]]
            self.turned.append(np.flatnonzero(np.isin(cols, p_dot)) if turned else None)
        self._jac = [_jacobian(net) for _, net, _, _ in self.parts]
        self._yaw = self.slices["e"].start + YAW

    @classmethod
    def from_trained(cls, trained, data, dt: float, horizon: int = 1, delay: int = 0,
                     frame: str = "world") -> "LearnedDynamics":
        """From a :class:`~sdexp.model.training.TrainedNets` and the dataset it was trained on;
        ``dt`` the control interval, ``horizon`` the frames between a net's input and target,
        ``delay`` the command delay and ``frame`` the frame they were trained with."""
        a = data.arrays if hasattr(data, "arrays") else data
        spread = np.asarray(a["s"], dtype=float).reshape(len(a["s"]), -1).std(axis=0) if "s" in a else None
        return cls(trained.nets, **state_sizes(data), alpha=dt * horizon, specs=trained.specs, dt=dt, delay=delay,
                   bend_spread=spread, frame=frame)

    # ------------------------------------------------------------------------------ torch
    def net_outputs(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        """Predicted next velocities per block, from z = concat(x, u) (..., n + m)."""
        out = {}
        for (block, net, idx, _), turned in zip(self.parts, self.turned):
            inp = z.index_select(-1, idx)
            if turned is None:
                out[block] = net(inp)
                continue
            yaw = z[..., self._yaw]   # h in the heading frame: p_dot turned in, its prediction back
            a, b = int(turned[0]), int(turned[-1]) + 1
            inp = torch.cat([inp[..., :a], turn(inp[..., a:b], yaw, -1.0), inp[..., b:]], -1)
            out[block] = turn(net(inp), yaw)
        return out

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

    def predict(self, x, commands) -> np.ndarray:
        """The state after one explicit step (``dt``) per command of ``commands`` (oldest first),
        from x: where the commands already sent but not yet acting take the body."""
        x = np.asarray(x, dtype=np.float64)
        for u in commands:
            x = x + self.dt * self.f(x, u)
        return x

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
        z = np.concatenate([x, u])
        for (block, _, _, cols), jac, turned in zip(self.parts, self._jac, self.turned):
            rows = np.arange(n)[sl[block]]
            if turned is None:
                y, g = jac(z[cols])
            else:
                y, g, dy_dyaw = self._turned_jacobian(jac, z, cols, turned)
                J[rows, self._yaw] = dy_dyaw / a
            J[np.ix_(rows, cols)] = g / a                # (1/alpha) d net / d inputs
            J[rows, rows] -= 1.0 / a                     # (1/alpha)(d net / d v - I)
            f0[rows] = (y - x[rows]) / a
        return f0, J[:, :n], J[:, n:]

    def _turned_jacobian(self, jac, z, cols, turned) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(y, dy/dz[cols], dy/dyaw) of a heading-frame net, y = Ry(yaw) net(.., Ry(yaw)^T p_dot, ..),
        by the chain rule: the yaw is no input of the net but turns its input and its output,
        dy/dyaw = Ry' net + Ry dnet/dp_dot_h (Ry')^T p_dot."""
        R, dR = rotation(z[self._yaw])
        inp = z[cols].copy()
        v = inp[turned]
        inp[turned] = R.T @ v
        y_h, g_h = jac(inp)
        g = R @ g_h
        g[:, turned] = g[:, turned] @ R.T
        return R @ y_h, g, dR @ y_h + R @ g_h[:, turned] @ dR.T @ v
