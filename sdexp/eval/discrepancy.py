"""``sdexp experiment=discrepancy drone=<d> discrepancy.measured=<dir>``: the discrepancy
workflow on measured logs (sdexp.discrepancy.workflow: localize, name, add, show)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

from sdexp.discrepancy.workflow import run_workflow
from sdexp.errors import UserError
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def run(run: Run) -> dict:
    from sdexp.sim.drone import build_drone

    cfg, out_dir = run.cfg, run.out_dir
    q = cfg.discrepancy
    if not q.measured:
        raise UserError("discrepancy.measured is not set: give the folder of measured logs "
                        "(sdexp experiment=record writes one)")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    rep = run_workflow(drone, cfg.drone, cfg.sim, cfg.noise, q, q.measured, Path(out_dir), cfg.cache_dir,
                       int(cfg.seed))
    log.info(json.dumps({k: rep[k] for k in ("verdict", "effects", "ties", "unexplained", "gap")}, indent=2))
    return {"verdict": rep["verdict"], "effects": [e["name"] for e in rep["effects"]],
            "gap_reduction": rep["gap"]["reduction"], "held_loss_before": rep["gap"]["held_loss_before"],
            "held_loss_after": rep["gap"]["held_loss_after"]}
