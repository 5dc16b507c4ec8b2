"""The residual MLP shared by d, g and h (supplement F, "Network Architecture and Training").

    z   = (input - in_mean) / in_std                       input standardisation
    h   = ReLU(W_in z + b_in)                              input layer (hidden wide)
    h   = ReLU(h + W2 ReLU(W1 h + b1) + b2)    x blocks    residual blocks, no normalisation
    r   = W_out h + b_out                                  output layer, no ReLU
    out = input[base] + out_mean + out_std * r             de-standardisation + current velocity

What the network predicts: the paper's networks map current to next-frame velocities
(s_dot -> s_dot_next, ...). Internally this one predicts the standardised *change* of the
velocity over one frame, ``(next - current - out_mean) / out_std``, and adds the current
velocity (the input channels listed in ``base``) back; so its output is the next-frame velocity
as the paper's, but the part it has to learn is the acceleration, in units of its own spread,
not a near-copy of its input. ``raw_output`` gives r, the quantity the training loss is taken
on. The standardisation statistics are buffers fitted on the training split
(:meth:`ResidualMLP.fit_scaling`), so a saved state dict is self-contained.
No normalisation layers (batch/layer norm) anywhere, as the supplement says.

``hidden = 0`` (``model.linear`` lists the nets built so): no hidden layers, r = W_out z + b_out,
a linear model trained and used exactly like the MLPs (why the rod needs it: README "Fixed-point
ablation").
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


class ResidualBlock(nn.Module):
    """linear, ReLU, linear, + skip, ReLU."""

    def __init__(self, width: int):
        super().__init__()
        self.fc1 = nn.Linear(width, width)
        self.fc2 = nn.Linear(width, width)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.relu(h + self.fc2(torch.relu(self.fc1(h))))


class ResidualMLP(nn.Module):
    def __init__(self, n_in: int, n_out: int, hidden: int = 128, blocks: int = 4,
                 base: Sequence[int] | None = None, prior: bool = False):
        """``base``: for every output channel the index of the input channel holding its current
        value (the residual is added to it); None = predict the output directly. ``prior``: a
        fixed affine map of the input added to it too (``prior_W`` x + ``prior_b``, buffers set by
        ``set_prior``: the rigid body's response, model.prior), so the net learns what it misses."""
        super().__init__()
        if n_in < 1 or n_out < 1:
            raise ValueError(f"ResidualMLP needs n_in >= 1 and n_out >= 1, got {n_in}, {n_out}")
        if hidden == 0:
            blocks = 0   # a linear model
        self.n_in, self.n_out, self.hidden, self.n_blocks = n_in, n_out, hidden, blocks
        self.inp = nn.Linear(n_in, hidden) if hidden else None
        self.blocks = nn.ModuleList(ResidualBlock(hidden) for _ in range(blocks))
        self.out = nn.Linear(hidden or n_in, n_out)
        if base is not None:
            base = list(base)
            if len(base) != n_out or not all(0 <= b < n_in for b in base):
                raise ValueError(f"base must give one input index per output, got {base}")
        self.has_base = base is not None
        self.register_buffer("base", torch.tensor(base if base is not None else [0] * n_out, dtype=torch.long))
        self.register_buffer("in_mean", torch.zeros(n_in))
        self.register_buffer("in_std", torch.ones(n_in))
        self.register_buffer("out_mean", torch.zeros(n_out))
        self.register_buffer("out_std", torch.ones(n_out))
        self.has_prior = bool(prior)
        if self.has_prior:   # only then: nets saved before priors existed load as they were
            self.register_buffer("prior_W", torch.zeros(n_out, n_in))
            self.register_buffer("prior_b", torch.zeros(n_out))

    @torch.no_grad()
    def set_prior(self, W, b) -> None:
        self.prior_W[:] = torch.as_tensor(W, dtype=self.prior_W.dtype)
        self.prior_b[:] = torch.as_tensor(b, dtype=self.prior_b.dtype)

    # ---------------------------------------------------------------------------- scaling
    def current(self, x: torch.Tensor) -> torch.Tensor:
        """What the residual is added to: the current value of every output channel (zeros
        without ``base``), plus the prior's prediction of its change where there is one."""
        if not self.has_base:
            out = torch.zeros(x.shape[:-1] + (self.n_out,), dtype=x.dtype, device=x.device)
        else:
            out = x.index_select(-1, self.base)
        if self.has_prior:
            out = out + x @ self.prior_W.to(x.dtype).T + self.prior_b.to(x.dtype)
        return out

    @torch.no_grad()
    def fit_scaling(self, x: torch.Tensor, y: torch.Tensor, eps: float = 1e-6) -> None:
        """Input and output statistics from training data x (N, n_in), y (N, n_out). A constant
        channel gets std 1 (it is only shifted), never a division by ~0."""
        def stats(a):
            mean, std = a.mean(0), a.std(0)
            return mean, torch.where(std > eps, std, torch.ones_like(std))
        self.in_mean[:], self.in_std[:] = stats(x.to(self.in_mean.dtype))
        self.out_mean[:], self.out_std[:] = stats((y - self.current(x)).to(self.out_mean.dtype))

    def target_raw(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The standardised change the output layer is trained to produce for target y."""
        return (y - self.current(x) - self.out_mean) / self.out_std

    # ---------------------------------------------------------------------------- forward
    def raw_output(self, x: torch.Tensor) -> torch.Tensor:
        h = (x - self.in_mean) / self.in_std
        if self.inp is not None:
            h = torch.relu(self.inp(h))
        for block in self.blocks:
            h = block(h)
        return self.out(h)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.current(x) + self.out_mean + self.out_std * self.raw_output(x)

    # ---------------------------------------------------------------------------- saving
    def spec(self) -> dict:
        """Constructor arguments: ``ResidualMLP(**net.spec())`` rebuilds the architecture."""
        return {"n_in": self.n_in, "n_out": self.n_out, "hidden": self.hidden, "blocks": self.n_blocks,
                "base": self.base.tolist() if self.has_base else None, **({"prior": True} if self.has_prior else {})}

    @classmethod
    def from_saved(cls, spec: dict, state: dict) -> "ResidualMLP":
        net = cls(**spec)
        net.load_state_dict(state)
        return net.eval()


class EnsembleMLP(nn.Module):
    """The mean of ResidualMLPs that read and predict the same channels (``model.ensemble``):
    each trained alike from its own seed, so what one net got from its initialisation and its
    held-out split averages out. Used wherever one ResidualMLP is (forward, n_in, n_out)."""

    def __init__(self, members: Sequence[ResidualMLP]):
        super().__init__()
        members = list(members)
        if not members or len({(m.n_in, m.n_out) for m in members}) != 1:
            raise ValueError("EnsembleMLP needs one or more nets of the same shape")
        self.members = nn.ModuleList(members)
        self.n_in, self.n_out = members[0].n_in, members[0].n_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([m(x) for m in self.members]).mean(0)
