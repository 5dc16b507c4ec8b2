"""``sdexp experiment=nsweep``: the relinearisation period n of Algorithm 1 (100/n Hz), swept over
the paper's {1, 2, 5, 10, 20, 30, 40, 50, 100} on the SOTA task (the flower to (3, 3, 3)).
Writes ``nsweep.csv`` (survival, final error, mean error over the last 5 s, thrust usage per n),
``nsweep.png`` (final error and survival against n; x, y, z over time per n)."""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.eval.controllers import ours
from sdexp.eval.flights import Setup, flight_table
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def run(run: Run) -> dict:
    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    setup = Setup(cfg)
    task = setup.task(np.asarray(p.start, float), np.asarray(p.target, float), float(p.seconds))
    rows, tables = [], {}
    for n in p.n_values:
        c = replace(cfg, control=replace(cfg.control, n=int(n)))
        sim = setup.simulator()
        flight, m = setup.fly(sim, ours(c, setup.dyn, setup.drone.max_thrust), task, f"n = {n}")
        tables[int(n)] = flight_table(flight, setup.dyn)
        rows.append({"n": int(n), "relinearization_hz": 1.0 / (int(n) * float(cfg.sim.control_dt)), **m})
        log.info(f"sdexp: n = {n}: survived {m['survival_time']:.2f} s, final error {m['final_error']:.3f} m")
    table = pd.DataFrame(rows)
    run.table(table, "nsweep")
    _plot(table, tables, np.asarray(p.target, float), out_dir / "nsweep.png", cfg.drone.name)
    out = {}
    for r in rows:
        out[f"n{r['n']}_final_error"] = r["final_error"]
        out[f"n{r['n']}_survival_time"] = r["survival_time"]
    return out


def _plot(table: pd.DataFrame, tables: dict, target: np.ndarray, path: Path, drone: str) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    ax = axes[0]
    ax.plot(table["n"], table["final_error"], "o-", label="final error")
    ax.plot(table["n"], table["mean_error_last_5s"], "s--", label="mean error, last 5 s")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("n (relinearise every n steps)")
    ax.set_ylabel("position error (m)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax = axes[1]
    ax.plot(table["n"], table["survival_time"], "o-")
    ax.set_xscale("log")
    ax.set_xlabel("n")
    ax.set_ylabel("survival time (s)")
    ax.grid(alpha=0.3, which="both")
    ax = axes[2]
    colors = plt.cm.viridis(np.linspace(0, 0.9, len(tables)))
    for (n, tab), c in zip(tables.items(), colors):
        err = np.linalg.norm(tab[[a for a in ("x", "y", "z") if a in tab]].to_numpy() - target, axis=1)
        ax.plot(tab["t"], err, color=c, label=f"n = {n}")
    ax.set_yscale("log")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("distance to target (m)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3, which="both")
    fig.suptitle(f"{drone}: relinearisation period sweep")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
