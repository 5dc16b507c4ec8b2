"""``sdexp experiment=sota``: the paper's SOTA comparison. The flower flies from (0, 0, 0) to
(3, 3, 3) for 20 s under each controller -- ours (Algorithm 1), rigid LQR, geometry-updating
LQR, neural controller -- with the same simulator, noise seed, task and thrust clip.

Writes ``sota.csv`` (our metrics beside the paper's; ``failure`` is why a flight ended early --
a blow-up, a controller failure or a loss of control, config ``flight`` -- and ``survival_time``
when), ``trajectory_<controller>.csv``, ``sota.png`` (the paper's figure: x, y, z over time per
controller, each titled with how its flight ended) and ours' median milliseconds per
relinearisation (``bench_control`` measures the rest).
"""
from __future__ import annotations

import logging
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.eval.flights import Setup, flight_table, position_plot

log = logging.getLogger(__name__)


# The paper's table (Experiments, "SOTA Comparison"): survival time (s), final error (m), thrust usage (N)
PAPER = {
    "ours": (20.0, 0.099, 26740.0),
    "rigid_lqr": (0.67, 29.744, 90596.0),
    "geometry_lqr": (0.69, 14.989, 61947.0),
    "neural": (0.19, 23.454, 179996.0),
}
LABELS = {"ours": "ours (relinearizing LQR)", "rigid_lqr": "LQR (rest shape)",
          "geometry_lqr": "geometry-updating LQR", "neural": "neural controller"}


def ending(m: dict, width: int = 48) -> str:
    """How a flight ended, for a figure title: survived, or the failure's time and reason."""
    if m["survived"]:
        return f"survived {m['survival_time']:.2f} s"
    return textwrap.fill(f"ended at {m['survival_time']:.2f} s: {m['failure']}", width)


def run(cfg, out_dir: Path) -> dict:
    p = cfg.experiment.params
    out_dir = Path(out_dir)
    setup = Setup(cfg)
    seconds = float(p.seconds)
    task = setup.task(np.asarray(p.start, float), np.asarray(p.target, float), seconds)
    rows, tables, titles, out = [], {}, {}, {}
    for name in p.controllers:
        sim = setup.simulator()
        ctl = setup.controller(name, sim)
        t0 = time.perf_counter()
        flight, m = setup.fly(sim, ctl, task, LABELS.get(name, name))
        wall = time.perf_counter() - t0
        tab = flight_table(flight, setup.dyn)
        tab.to_csv(out_dir / f"trajectory_{name}.csv", index=False)
        tables[name] = tab
        ps, pe, pu = PAPER.get(name, (np.nan,) * 3)
        rows.append({"controller": name, **m, "paper_survival_time": ps, "paper_final_error": pe,
                     "paper_thrust_usage": pu, "wall_seconds": wall})
        titles[name] = f"{LABELS.get(name, name)}\n{ending(m)}\nfinal error {m['final_error']:.2f} m"
        out.update({f"{name}_{k}": v for k, v in m.items()})
        if name == "ours" and ctl.timings:
            out["ours_ms_per_relinearization"] = 1e3 * float(np.median(ctl.timings))
        log.info(f"sdexp: {name}: survived {m['survival_time']:.2f} s ({m['failure'] or 'whole flight'}), "
                 f"final error {m['final_error']:.3f} m, thrust usage {m['thrust_usage']:.0f} N")
    table = pd.DataFrame(rows)
    table.to_csv(out_dir / "sota.csv", index=False)
    position_plot(tables, titles, out_dir / "sota.png",
                  f"{cfg.drone.name}: {list(p.start)} -> {list(p.target)} in {seconds:g} s")
    return out
