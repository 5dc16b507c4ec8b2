"""Where and when does an unmodelled push act? A diagnostic, not a candidate.

For every window, the constant external linear acceleration a and angular acceleration alpha of
the whole body (about its centre of mass) that best explain what the simulator, with the named
effects, still gets wrong: per-window least squares on a finite-difference Jacobian (one rollout
per component, shared by all windows, since each window's response is its own), checked by one
rollout with every window's own push. A wind gust shows as a horizontal push that wanders over a
flight; a hanging weight as a downward one that swings; a one-sided drag as a torque that grows
with speed. The fit is per window on that window's own data, so it always helps a little: it
says where a push would act, not that one exists (that is the held-out test's job).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from sdexp.discrepancy.fit import per_window
from sdexp.sim.physics.effects import Effect

STEP = 0.5   # m/s^2 and rad/s^2: the finite-difference step, a push a sensor sees in 0.2 s


class Push(Effect):
    """A uniform linear acceleration plus a rigid angular acceleration about the centre of mass,
    as mass-proportional vertex forces: m_i (a + alpha x r_i)."""
    name = "push"

    def __init__(self, dim: int):
        self.dim = dim
        self.values = np.zeros(components(dim))

    def body_forces(self, sim, f):
        if not np.any(self.values):
            return
        m = sim.fem.mass
        x = sim.body.x
        r = x - m @ x / m.sum()
        a, al = self.values[:self.dim], self.values[self.dim:]
        spin = np.cross(al, r) if self.dim == 3 else al[0] * np.c_[-r[:, 1], r[:, 0]]
        f += m[:, None] * (a + spin)


def components(dim: int) -> int:
    return 6 if dim == 3 else 3


def names(dim: int) -> list[str]:
    lin = ["a_x", "a_y", "a_z"][:dim]
    return lin + (["alpha_x", "alpha_y", "alpha_z"] if dim == 3 else ["alpha"])


def estimate(pred, windows, sigma, effects, r0, ridge: float = 1e-2) -> pd.DataFrame:
    """One row per window: its flight, start time, the push (a, alpha) and the normalised loss
    before and after it (after: from the rollout with every window's own push). ``r0`` is the
    residual with ``effects`` alone. ``ridge`` (in units of the finite-difference step) keeps a
    push that no channel sees at zero."""
    dim = pred.drone.dim
    push = Push(dim)
    W = windows.count

    def moved(j):
        push.values[:] = 0.0
        push.values[j] = STEP
        return list(effects) + [push]
    theta, _ = per_window(pred, windows, sigma, r0, moved, components(dim), STEP, ridge)

    def set_push(w):
        push.values[:] = theta[w]
    after = pred.residual(windows, list(effects) + [push], before=set_push)
    starts = np.concatenate([f.t[s] for f, s in zip(windows.flights, windows.starts) if len(s)]) \
        if windows.count else np.zeros(0)
    table = pd.DataFrame(theta, columns=names(dim))
    table.insert(0, "t", starts)
    table.insert(0, "flight", [windows.flights[i].name for i in windows.flight_of])
    table["loss_before"] = np.mean((r0 / sigma).reshape(W, -1) ** 2, axis=1)
    table["loss_after"] = np.mean((after / sigma).reshape(W, -1) ** 2, axis=1)
    return table


def summary(table: pd.DataFrame, floor_loss: float, dim: int) -> dict:
    """Mean and spread of the push over windows, and the share of the windows' excess over the
    noise floor that a per-window push removes."""
    cols = names(dim)
    excess = float(np.sum(np.maximum(table.loss_before - floor_loss, 0.0)))
    removed = float(np.sum(table.loss_before - table.loss_after))
    return {"mean": dict(zip(cols, table[cols].mean().round(4).tolist())),
            "std": dict(zip(cols, table[cols].std(ddof=1).round(4).tolist())) if len(table) > 1 else {},
            "share_of_excess_removed": float(min(removed / excess, 1.0)) if excess > 0 else None,
            "windows": int(len(table))}


def plot(table: pd.DataFrame, path, dim: int, title: str) -> None:
    """The push over each flight's windows: linear (top) and angular (bottom) acceleration."""
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    cols = names(dim)
    fig, axes = plt.subplots(2, 1, figsize=(9, 4.5), sharex=True)
    offset, ticks = 0.0, []
    for fl, g in table.groupby("flight", sort=False):
        t = g.t.to_numpy() - g.t.min() + offset
        for ax, part in ((axes[0], cols[:dim]), (axes[1], cols[dim:])):
            for j, c in enumerate(part):
                ax.plot(t, g[c], ".-", color=f"C{j}", lw=1, ms=3, label=c if offset == 0 else None)
        ticks.append((offset, fl))
        offset = t.max() + 1.0
    for ax, unit in ((axes[0], "push (m/s^2)"), (axes[1], "turn (rad/s^2)")):
        ax.axhline(0, color="k", lw=0.5)
        for x0, _ in ticks[1:]:
            ax.axvline(x0 - 0.5, color="0.7", lw=0.5)
        ax.set_ylabel(unit)
        ax.legend(fontsize=7, ncol=3)
    axes[0].set_title(title, fontsize=9)
    axes[1].set_xlabel("window start, flights strung together (s)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
