"""``sdexp experiment=ablation_fixed_point``: the paper's online-relinearisation ablation. The rod
translates ``distance`` m along +X. A fixed point (x*, u*) of the learned dynamics is found by
trial and refined by gradient descent (sdexp.control.fixed_point); the goal is that fixed point
moved to the target location, then polluted by uniform noise proportional to every variable
(10 ... 80%, the location untouched). Each polluted goal is flown twice: linearised once at the
polluted (x_goal, u_goal) (``relinearize=False``) and with Algorithm 1's online relinearisation.
Both start from u = u_goal.

Writes ``ablation_fixed_point.csv`` (per level and mode: survival, final error, thrust usage,
whether the command went non-finite) and ``ablation_fixed_point.png`` (x over time per level,
without / with relinearisation side by side, as the paper's figure).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.control.fixed_point import find_fixed_point, pollute
from sdexp.eval.controllers import ours
from sdexp.eval.flights import Setup, flight_table
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def run(run: Run) -> dict:
    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    setup = Setup(cfg)
    dyn, tmax = setup.dyn, setup.drone.max_thrust
    start = np.zeros(dyn.dim)
    target = start.copy()
    target[0] += float(p.distance)
    x_star, u_star, residual = find_fixed_point(dyn, target, tmax, int(cfg.seed), int(p.trials), int(p.descent_steps))
    log.info(f"sdexp: fixed point |f(x*, u*)| = {residual:.3g}, u* = {np.round(u_star, 3).tolist()}")
    rng = np.random.default_rng(int(cfg.seed))
    rows, tables = [], {}
    for level in p.noise_levels:
        x_goal, u_goal = pollute(x_star, u_star, float(level), dyn.slices["p"], rng)
        # the goal is the polluted fixed point's configuration (s, e) at the target location
        task = setup.task(start, target, float(p.seconds), bend_times=[0.0], bend_targets=[x_goal[dyn.slices["s"]]],
                          attitude=x_goal[dyn.slices["e"]])
        for relin in (False, True):
            sim = setup.simulator()
            ctl = ours(cfg, dyn, tmax, relinearize=relin, x_op=x_goal, u_op=u_goal, u0=u_goal)
            mode = "relinearized" if relin else "fixed"
            flight, m = setup.fly(sim, ctl, task, f"{mode}, noise {level:g}")
            tab = flight_table(flight, dyn)
            tables[(mode, float(level))] = tab
            rows.append({"noise": float(level), "mode": mode, **m,
                         "nan_command": m["failure"] == "controller: non-finite command"})
    table = pd.DataFrame(rows)
    run.table(table, "ablation_fixed_point")
    _plot(tables, float(target[0]), out_dir / "ablation_fixed_point.png", cfg.drone.name)
    out = {"fixed_point_residual": residual}
    for r in rows:
        key = f"{r['mode']}_{int(round(100 * r['noise']))}"
        out[f"{key}_final_error"] = r["final_error"]
        out[f"{key}_survival_time"] = r["survival_time"]
    return out


def _plot(tables: dict, target_x: float, path: Path, drone: str) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    levels = sorted({lv for _, lv in tables})
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(levels)))
    for ax, mode in zip(axes, ("fixed", "relinearized")):
        for lv, c in zip(levels, colors):
            tab = tables.get((mode, lv))
            if tab is not None:
                ax.plot(tab["t"], tab["x"], color=c, label=f"{100 * lv:.0f}% noise")
        ax.axhline(target_x, color="k", ls="--", lw=0.8)
        ax.set_title(f"{'linearised once at the polluted fixed point' if mode == 'fixed' else 'online relinearisation'}",
                     fontsize=10)
        ax.set_xlabel("t (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("x (m); dashed: target")
    axes[1].legend(fontsize=8)
    fig.suptitle(f"{drone}: translate {target_x:g} m along +X with a polluted fixed point as the goal")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
