"""``sdexp experiment=sota``: the paper's SOTA comparison. The flower flies from (0, 0, 0) to
(3, 3, 3) for 20 s under each controller -- ours (Algorithm 1), rigid LQR, geometry-updating
LQR, neural controller -- with the same simulator, noise seed, task and thrust clip.

Writes ``sota.csv`` (our metrics beside the paper's; ``failure`` is why a flight ended early --
a blow-up, a controller failure or a loss of control, config ``flight`` -- and ``survival_time``
when), ``trajectory_<controller>.csv``, ``sota.png`` (the paper's figure: x, y, z over time per
controller, each titled with how its flight ended) and ours' median milliseconds per
relinearisation (``bench_control`` measures the rest). The controllers listed in
``experiment.params.animate`` (default ours) also get ``sota_<controller>.mp4`` (the deforming
drone in flight) and ``sota_<controller>_vtu/sota_<controller>.pvd`` (its mesh series for ParaView).
"""
from __future__ import annotations

import logging
import time

import numpy as np
import pandas as pd

from sdexp.eval.flights import Setup, ending, flight_table, position_plot
from sdexp.experiment_params import SotaParams
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


# The paper's table (Experiments, "SOTA Comparison"): survival time (s), final error (m), thrust usage (N)
PAPER = {
    "ours": (20.0, 0.099, 26740.0),
    "rigid_lqr": (0.67, 29.744, 90596.0),
    "geometry_lqr": (0.69, 14.989, 61947.0),
    "neural": (0.19, 23.454, 179996.0),
}
LABELS = {"ours": "ours (relinearizing LQR)", "rigid_lqr": "LQR (rest shape)",
          "geometry_lqr": "geometry-updating LQR", "neural": "neural controller",
          "reduced_lqr": "reduced-model LQR (privileged)"}


def _paper_ending(survival: float, seconds: float) -> str:
    return f"survived {survival:g} s" if survival >= seconds else f"failed at {survival:g} s"


def run(run: Run) -> dict:
    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    setup = Setup(cfg)
    seconds = float(p.seconds)
    task = setup.task(np.asarray(p.start, float), np.asarray(p.target, float), seconds)
    rows, tables, titles, out = [], {}, {}, {}
    animate = set(p.animate)
    for name in p.controllers:
        sim = setup.simulator()
        ctl = setup.controller(name, sim)
        rec = setup.recorder(name in animate)
        t0 = time.perf_counter()
        flight, m = setup.fly(sim, ctl, task, LABELS.get(name, name), recorder=rec)
        wall = time.perf_counter() - t0
        setup.animate(out_dir, f"sota_{name}", rec, f"{cfg.drone.name}: {LABELS.get(name, name)}, "
                      f"{list(p.start)} -> {list(p.target)}; {ending(m)}")
        tab = flight_table(flight, setup.layout)
        run.table(tab, f"trajectory_{name}")
        tables[name] = tab
        ps, pe, pu = PAPER.get(name, (np.nan,) * 3)
        rows.append({"controller": name, **m, "paper_survival_time": ps, "paper_final_error": pe,
                     "paper_thrust_usage": pu, "wall_seconds": wall})
        titles[name] = (f"{LABELS.get(name, name)}: {ending(m)}, {m['final_error']:.2f} m off\n"
                        f"paper: {_paper_ending(ps, seconds)}, {pe:g} m off")
        out.update({f"{name}_{k}": v for k, v in m.items()})
        if name in ("ours", "reduced_lqr") and ctl.timings:
            out[f"{name}_ms_per_relinearization"] = 1e3 * float(np.median(ctl.timings))
        log.info(f"sdexp: {name}: survived {m['survival_time']:.2f} s ({m['failure'] or 'whole flight'}), "
                 f"final error {m['final_error']:.3f} m, thrust usage {m['thrust_usage']:.0f} N")
    table = pd.DataFrame(rows)
    run.table(table, "sota")
    position_plot(tables, titles, out_dir / "sota.png",
                  f"{cfg.drone.name}: {list(p.start)} -> {list(p.target)} in {seconds:g} s (seed {cfg.seed})", seconds)
    return out


def summary(params: SotaParams, metrics: dict) -> str:
    """Ours and the baselines beside the paper's table, rounded."""
    rows = [f"  {'controller':<24}{'survival (s)':>14}{'paper':>8}{'final error (m)':>17}{'paper':>9}"]
    for name in params.controllers:
        if f"{name}_survival_time" not in metrics:
            continue
        ps, pe, _ = PAPER.get(name, (float("nan"),) * 3)
        rows.append(f"  {LABELS.get(name, name):<24}{metrics[f'{name}_survival_time']:>14.2f}{ps:>8.2f}"
                    f"{metrics[f'{name}_final_error']:>17.3f}{pe:>9.3f}")
    return "\n".join(rows)
