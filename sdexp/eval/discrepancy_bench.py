"""``sdexp experiment=discrepancy_bench``: the discrepancy workflow on logs with hidden effects
(sdexp.discrepancy.bench: the scenarios, their scoring and the summary)."""
from __future__ import annotations

import json
import logging

from sdexp.discrepancy.bench import check as check_bench, run_bench
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def check(run: Run) -> None:
    """The bench's parameters against the drone and the folders, before anything is written."""
    cfg = run.cfg
    check_bench(run.params, run.out_dir, cfg.drone, cfg.sim, cfg.cache_dir, int(cfg.seed))


def run(run: Run) -> dict:
    from sdexp.log import Phase

    cfg, p = run.cfg, run.params
    with Phase("discrepancy_bench scenarios", unit="scenarios") as bar:
        metrics = run_bench(cfg.drone, cfg.sim, cfg.noise, cfg.discrepancy, p, run.out_dir, cfg.cache_dir,
                            int(cfg.seed), int(p.workers), progress=bar.update)
    log.info(json.dumps(metrics, indent=2))
    return metrics
