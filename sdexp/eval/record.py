"""``sdexp experiment=record``: flight logs of a drone in the format the discrepancy workflow
reads (sdexp.discrepancy.record), with the simulator as configured (its sim.effects included)."""
from __future__ import annotations

import logging

from sdexp.discrepancy.record import record_flights
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def run(run: Run) -> dict:
    """The experiment: record discrepancy.record.flights logs of cfg.drone with the simulator
    as configured (sim.effects included) into <run dir>/logs."""
    import json
    from sdexp.sim.drone import build_drone

    cfg = run.cfg
    r = cfg.discrepancy.record
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    folder = run.path("logs")
    paths = record_flights(drone, cfg.sim, cfg.noise, folder, int(r.flights), float(r.seconds),
                           list(r.manoeuvres), int(cfg.seed), float(r.height), float(r.ground),
                           float(r.amplitude))
    meta = json.loads((folder / "meta.json").read_text())
    log.info(f"sdexp: wrote {len(paths)} flights to {folder}")
    return {"flights": len(paths), "logs": str(folder), "failures": len(meta["failures"])}
