"""``sdexp experiment=report sweep_dir=<folder>``: statistics over a sweep's jobs.

Reads every job folder under the sweep folder (metrics.json + config.yaml), groups the jobs by
the config values that differ between them other than the seed, and writes

* ``stats.csv``: one row per group and metric: n, mean, std, the Student-t confidence interval
  (the method is in the ``method`` column) and, for booleans, counts ("ours survived 5 of 5");
* ``stats.png``: per metric group (final error, survival time, ...) the means with their
  intervals as error bars.

See :mod:`sdexp.eval.stats` for the functions behind it.
"""
from __future__ import annotations

import logging
from pathlib import Path

from sdexp.errors import UserError
from sdexp.eval import stats
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def _params(p):
    if p.sweep_dir is None or str(p.sweep_dir).strip() == "":
        raise UserError("experiment.params.sweep_dir is not set: name the sweep to aggregate, e.g. "
                        "sdexp experiment=report sweep_dir=multirun/sota/<time>")
    return Path(str(p.sweep_dir)).expanduser(), float(p.confidence)


def check(run: Run) -> None:
    """Before the run folder is written: the sweep folder exists and holds finished jobs."""
    sweep_dir, _ = _params(run.params)
    stats.find_jobs(sweep_dir, run.out_dir)
    if run.params.scatter:
        stats.check_metrics(stats.grouped_jobs(sweep_dir, run.out_dir)[0], list(run.params.scatter), sweep_dir)


def run(run: Run) -> dict:
    sweep_dir, confidence = _params(run.params)
    table = stats.aggregate(sweep_dir, confidence, run.out_dir)
    csv = run.table(table, "stats", float_format="%.6g")
    stats.plot(table, run.path("stats.png"), title=sweep_dir.resolve().name)
    if run.params.scatter:
        stats.scatter(sweep_dir, list(run.params.scatter), run.path("scatter.png"),
                      None if run.params.scatter_lines is None else list(run.params.scatter_lines),
                      run.out_dir, sweep_dir.resolve().name)
    groups = list(dict.fromkeys(table["group"]))
    jobs = int(table.drop_duplicates("group")["jobs"].sum()) if len(table) else 0
    log.info(f"sdexp: report over {jobs} jobs in {len(groups)} group{'s' if len(groups) != 1 else ''} "
             f"of {sweep_dir.resolve()} -> {csv}")
    for group in groups:
        rows = table[table["group"] == group]
        log.info(f"  {group}:")
        for _, r in rows.iterrows():
            log.info(f"    {r['metric']}: {r['summary']}")
    return {"sweep_dir": str(sweep_dir.resolve()), "jobs": jobs, "groups": len(groups),
            "metrics": int(table["metric"].nunique()) if len(table) else 0, "confidence": confidence}
