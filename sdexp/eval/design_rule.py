"""``sdexp experiment=design_rule``: where the paper leaves a design open, the rule that chooses it
from statics, never from a controller (issue 52; docs/designs.md).

The paper fixes each design's mass, modulus, bounding lengths, rotor and sensor counts and
maximum thrust (supplement B's table) and asks of its designs only that they be "soft enough to
perform significant deformation, while the deformation mode ... is simple" (supplement D). It
leaves open where the rotors sit (the orange peel; every outline of the 2D designs is sdexp's
drawing) and how thick a plate is. The rule: **a design must hover statically with margin** --
the thrust that lifts the weight of the shape it bends the body into (``statics.static_hover``:
the full FEM with the rigid motion taken out) uses at most 60% of a rotor's range and leaves a
settled fold of at most 45 deg (``statics.RULE_*``). Of the candidates of ``designs.<drone>.grid``
(every combination), the rule keeps the passing one **nearest the drawing** (``drawn``; relative
change summed over the keys; ties to the smaller thrust share): the drawing changes only as much
as the statics demand.

Writes ``design_rule.csv`` (one row per candidate: its values, the static hover's figures, the
rule's verdict, the distance to the drawing, which one is chosen) and ``design_rule.png``; the log
says for each drone whether its committed config is the rule's choice."""
from __future__ import annotations

import itertools
import logging
from dataclasses import replace

import numpy as np
import pandas as pd

from sdexp import conf
from sdexp.errors import UserError
from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def check(run: Run) -> None:
    """Before anything is written: every drone named, every key one the rule may choose (the
    thickness, or one of the drone's shape's proportions, drone.params)."""
    names = conf.names("drone")
    for name, design in _designs(run.params).items():
        if name not in names:
            raise UserError(f"experiment.params.designs.{name}: {name!r} is not a drone: choose one of {', '.join(names)}")
        drone = conf.drone(name)
        for key in list(design["grid"]) + list(design.get("drawn", {})):
            _value(drone, key, f"experiment.params.designs.{name}")


def _designs(p) -> dict:
    """The designs of ``drones`` (null: every one of ``designs``)."""
    return {n: p.designs[n] for n in (p.drones if p.drones is not None else p.designs)}


def _value(drone, key: str, where: str) -> float:
    """The drone config's value of ``key``: one of its shape's proportions (drone.params) or its
    thickness."""
    if key in drone.params:
        return float(drone.params[key])
    if key != "thickness":
        raise UserError(f"{where}: {key} is not a design the rule may choose: allowed thickness or one of "
                        f"the {drone.shape} shape's proportions ({', '.join(drone.params)})")
    return float(drone.thickness)


def with_values(drone, values: dict):
    """The drone config with ``values`` (key -> value: a proportion of its shape, or thickness) set."""
    params = {**drone.params, **{k: v for k, v in values.items() if k != "thickness"}}
    return replace(drone, params=params, **{k: v for k, v in values.items() if k == "thickness"})


def candidates(grid: dict) -> list[dict]:
    keys = list(grid)
    return [dict(zip(keys, map(float, combo))) for combo in itertools.product(*(grid[k] for k in keys))]


def distance(values: dict, drawn: dict) -> float:
    """Relative change from the drawing, summed over the keys (absolute where the drawing's is 0)."""
    return float(sum(abs(v - drawn[k]) / (abs(drawn[k]) or 1.0) for k, v in values.items()))


def candidate_row(cfg, name: str, values: dict, report=None) -> dict:
    from sdexp.sim.drone import build_drone
    from sdexp.sim.rigid.statics import static_hover

    row = {"drone": name, **values}
    try:
        drone = build_drone(with_values(conf.drone(name), values), cfg.cache_dir, cfg.sim.element)
    except UserError as err:   # a candidate its shape refuses is a row with the reason, not the end of the run
        row["design_rule"] = f"not built: {err}"
    else:
        hover = static_hover(drone, cfg.sim, seconds=float(cfg.experiment.params.seconds), cache_dir=cfg.cache_dir)
        row.update(hover.row(), thrust=" ".join(f"{u:.2f}" for u in hover.thrust))
    if report is not None:
        report(1)
    return row


def run(run: Run) -> dict:
    from sdexp.log import Phase
    from sdexp.parallel import run_spawned

    cfg, p = run.cfg, run.params
    tasks, drawn = [], {}
    for name, design in _designs(p).items():
        drone = conf.drone(name)
        drawn[name] = {k: float(design.get("drawn", {}).get(k, _value(drone, k, f"experiment.params.designs.{name}")))
                       for k in design["grid"]}
        tasks += [(cfg, name, values) for values in candidates(design["grid"])]
    with Phase("design rule candidates", total=len(tasks), unit="candidates") as bar:
        rows = run_spawned(candidate_row, tasks, max(1, min(int(p.workers), len(tasks))),
                           bar.update)
    table = pd.DataFrame(rows)
    table["distance"] = [distance({k: r[k] for k in drawn[r["drone"]]}, drawn[r["drone"]]) for r in rows]
    table["passes"] = table["design_rule"] == "holds"
    table["chosen"] = False
    metrics = {}
    for name in drawn:
        mine = table[table["drone"] == name]
        ok = mine[mine["passes"]]
        committed = {k: _value(conf.drone(name), k, f"experiment.params.designs.{name}") for k in drawn[name]}
        if ok.empty:
            log.warning(f"sdexp: design rule: no candidate of {name} hovers statically with margin; its "
                        f"committed design stays ({_say(committed)})")
            metrics[f"{name}_chosen"] = None
            continue
        best = ok.sort_values(["distance", "static_hover_share"], kind="stable").index[0]
        table.loc[best, "chosen"] = True
        choice = {k: float(table.loc[best, k]) for k in drawn[name]}
        agrees = all(np.isclose(choice[k], committed[k]) for k in choice)
        log.info(f"sdexp: design rule: {name}: {_say(choice)} (drawn {_say(drawn[name])}): static hover "
                 f"{table.loc[best, 'static_hover_share']:.2f} of Tmax, fold {table.loc[best, 'static_hover_fold_deg']:.1f} "
                 f"deg; {len(ok)} of {len(mine)} candidates pass; conf/drone/{name}.yaml "
                 + ("has it" if agrees else f"has {_say(committed)}: not the rule's choice"))
        metrics.update({f"{name}_{k}": v for k, v in choice.items()})
        metrics[f"{name}_committed_is_chosen"] = bool(agrees)
        metrics[f"{name}_passing"] = int(len(ok))
    run.table(table, "design_rule")
    design_plot(table, drawn, run.out_dir / "design_rule.png")
    return metrics


def _say(values: dict) -> str:
    return ", ".join(f"{k} {v:g}" for k, v in values.items())


def design_plot(table: pd.DataFrame, drawn: dict, path) -> None:
    """Per drone (a column), its candidates from the drawing outwards (by distance): above, the
    static hover's largest rotor thrust over Tmax; below, its settled fold; the rule's bounds as
    dashed lines, passing candidates green, failing red, a hold that failed a cross at the top;
    the drawing ringed, the rule's choice starred."""
    from sdexp.figures import pyplot, save_figure
    from sdexp.sim.rigid.statics import RULE_MAX_FOLD_DEG, RULE_MAX_SHARE
    plt = pyplot()

    names = list(drawn)
    fig, axes = plt.subplots(2, len(names), figsize=(0.32 * max(12, len(table)) + 2.0, 6.0), squeeze=False,
                             sharex="col", gridspec_kw={"width_ratios": [max(3, (table["drone"] == n).sum()) for n in names]})
    for col, name in enumerate(names):
        mine = table[table["drone"] == name].sort_values("distance", kind="stable").reset_index(drop=True)
        for row, (column, bound, top, label) in enumerate((("static_hover_share", RULE_MAX_SHARE, 1.05, "thrust share"),
                                                           ("static_hover_fold_deg", RULE_MAX_FOLD_DEG, 95.0, "fold (deg)"))):
            ax = axes[row, col]
            ax.axhline(bound, color="k", ls="--", lw=0.8)
            for i, r in mine.iterrows():
                value = r.get(column, np.nan)
                failed = not np.isfinite(value)
                y = top * 0.95 if failed else min(float(value), top)
                ax.plot(i, y, "x" if failed else "o", color="#1a9850" if r["passes"] else "#d73027", ms=7)
                if i == 0 and r["distance"] == 0:
                    ax.plot(i, y, "o", mfc="none", mec="k", ms=14)
                if r["chosen"]:
                    ax.plot(i, y, "*", color="k", ms=15)
            ax.set_ylim(0, top)
            ax.set_ylabel(label if col == 0 else "")
        axes[0, col].set_title(f"{name}: ring = the drawing, star = the rule's choice, x = the hold failed", fontsize=8)
        axes[1, col].set_xticks(range(len(mine)))
        axes[1, col].set_xticklabels([", ".join(f"{r[k]:g}" for k in drawn[name]) for _, r in mine.iterrows()],
                                     rotation=70, fontsize=7)
        axes[1, col].set_xlabel(", ".join(drawn[name]) + " (nearest the drawing first)",
                                fontsize=8)
    save_figure(fig, path)
