"""``sdexp experiment=discrepancy_bench``: the workflow on logs with hidden effects.

Scenarios: every library effect at two strengths and several seeds, null scenarios (the
nominal simulator), a few two-effect combinations and a few effects outside the library
(``unmodelled``: the honest answer is ``unexplained``). Each scenario records logs with the
hidden effects, keeps the label to itself, runs the workflow on the logs only and compares.
Writes scenarios.csv, confusion.csv/png, metrics (top-1 accuracy, null false-positive rate,
parameter error, held-out gap reduction) and the wall time.
"""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from sdexp.cache import atomic_write
from sdexp.discrepancy import bench_effects
from sdexp.errors import FULL, UserError, one_line
from sdexp.sim.physics.effects import LIBRARY

log = logging.getLogger(__name__)


COMBOS = [("rotor_drag", "motor_lag"), ("payload", "imu_bias"), ("wind", "ground_effect")]


def effect_entry(name: str, level: int, rng, drone) -> dict:
    """The library effect ``name`` at its moderate (level 0) or strong (1) bench strength, its
    effect's ``bench_strengths``; direction-like parts drawn from ``rng``."""
    key, *values = LIBRARY[name].bench_strengths
    v = values[level]
    dim = drone.dim
    if name == "wind":
        d = rng.normal(size=2 if dim == 3 else 1)
        d /= np.linalg.norm(d)
        vel = np.zeros(dim)
        vel[[0, 2] if dim == 3 else [0]] = v * d
        return {"name": "wind", "velocity": vel.tolist()}
    if name == "thrust_loss":
        return {"name": name, "rotor": int(rng.integers(drone.num_rotors)), "fraction": v}
    if name == "payload":
        ext = np.ptp(drone.fem.rest, axis=0)
        point = drone.fem.mass @ drone.fem.rest / drone.fem.mass.sum()
        point[0] += rng.uniform(-0.25, 0.25) * ext[0]
        if dim == 3:
            point[2] += rng.uniform(-0.25, 0.25) * ext[2]
        return {"name": name, "mass": v, "point": point.tolist()}
    if name == "imu_bias":
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        value = [v * d[0], 0.0, v * d[1]] if dim == 3 else [v * d[0]]
        return {"name": name, "channel": "rot", "value": value}
    if name == "rotor_reaction_torque":
        return {"name": name, "k": v * rng.choice([-1.0, 1.0])}
    return {"name": name, key: v}


def scenarios(drone, names, seeds: int, nulls: int, combos: bool, unmodelled: int, seed0: int = 0,
              levels=(0, 1), variants: int = 0) -> list[dict]:
    """Library effects (``names`` x ``levels`` x ``seeds``), ``nulls``, two-effect ``combos``,
    and per seed (``variants``, ``unmodelled``) every outside-the-library effect of
    sdexp.discrepancy.bench_effects, with or without a fair library answer."""
    out = []
    k = 0
    for name in names:
        for level in levels:
            for s in range(seeds):
                rng = np.random.default_rng([seed0, k])
                out.append({"id": f"{name}-{'ab'[level]}{s}", "kind": "single", "truth": [name],
                            "effects": [effect_entry(name, level, rng, drone)], "seed": seed0 + 1000 + k})
                k += 1
    for s in range(nulls):
        out.append({"id": f"null-{s}", "kind": "null", "truth": [], "effects": [], "seed": seed0 + 1000 + k})
        k += 1
    for a, b in (COMBOS if combos else []):
        if a in names and b in names:
            rng = np.random.default_rng([seed0, k])
            out.append({"id": f"{a}+{b}", "kind": "combo", "truth": [a, b],
                        "effects": [effect_entry(a, 1, rng, drone), effect_entry(b, 1, rng, drone)],
                        "seed": seed0 + 1000 + k})
            k += 1
    for s in range(variants):
        rng = np.random.default_rng([seed0, k])
        for vid, answer, entry in bench_effects.variants(drone, rng):
            out.append({"id": f"{vid}-{s}", "kind": "variant", "truth": [answer], "effects": [entry],
                        "seed": seed0 + 1000 + k})
            k += 1
    for s in range(unmodelled):
        rng = np.random.default_rng([seed0, k])
        for uid, entry in bench_effects.unmodelled(drone, rng):
            out.append({"id": f"{uid}-{s}", "kind": "unmodelled", "truth": [uid], "effects": [entry],
                        "seed": seed0 + 1000 + k})
            k += 1
    return [dict(sc, effects=portable(sc["effects"])) for sc in out]


def portable(x):
    """``x`` with every float rounded to 12 significant digits: a scenario drawn from the same
    seed must be the same scenario on every machine, and some of its numbers are reductions
    whose last bits follow the CPU's BLAS kernels (a payload's point is mass @ rest); a row
    finished on one machine is then found again by its key on another."""
    if isinstance(x, float):
        return float(f"{x:.12g}")
    if isinstance(x, dict):
        return {k: portable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [portable(v) for v in x]
    return x


def select(scs: list[dict], only) -> list[dict]:
    """The scenarios named in ``only`` (experiment.params.only; None: all). Taken from the whole
    list, so each keeps its draws (they follow its place in the list) and its finished row."""
    if not only:
        return scs
    ids = [sc["id"] for sc in scs]
    unknown = [i for i in only if i not in ids]
    if unknown:
        raise UserError(f"experiment.params.only: unknown scenario(s) {unknown}; this bench's are {ids}")
    return [sc for sc in scs if sc["id"] in set(only)]


FAILED = "failed"   # the verdict of a scenario that raised: its row says why (``error``), the bench goes on


def run_scenario(sc: dict, drone_cfg, sim_cfg, noise_cfg, dcfg, out_dir: str, cache_dir: str, report=None) -> dict:
    """Record the scenario's logs with its hidden effects, run the workflow, compare. A scenario
    that raises is a row with verdict ``failed`` and its ``error`` (not kept for resuming: a
    rerun tries it again); a full disk ends the bench (every scenario after it would fail too)."""
    t0 = time.perf_counter()
    try:
        row = _scenario_row(sc, drone_cfg, sim_cfg, noise_cfg, dcfg, out_dir, cache_dir, t0)
    except Exception as err:   # noqa: BLE001 - one scenario's failure is its row, not the bench's end
        if isinstance(err, OSError) and err.errno in FULL:
            raise
        log.warning(f"discrepancy_bench: scenario {sc['id']} failed: {type(err).__name__}: {one_line(err)}")
        row = {"id": sc["id"], "kind": sc["kind"], "truth": "+".join(sc["truth"]) or "none", "verdict": FAILED,
               "top1": FAILED, "named": "", "ties": "", "seconds": time.perf_counter() - t0,
               "true_effects": json.dumps(sc["effects"]), "fitted": "[]",
               "error": f"{type(err).__name__}: {one_line(err)}"}
    if report:
        report(1)
    return row


def _scenario_row(sc: dict, drone_cfg, sim_cfg, noise_cfg, dcfg, out_dir: str, cache_dir: str, t0: float) -> dict:
    from sdexp.discrepancy.record import record_flights
    from sdexp.discrepancy.workflow import run_workflow
    from sdexp.sim.drone import build_drone

    folder = Path(out_dir) / sc["id"]
    key = scenario_key(sc, drone_cfg, sim_cfg, noise_cfg, dcfg)
    row = finished_row(folder, key)
    if row is not None:   # a run killed after this scenario resumes here (as does one that shares scenario_dir)
        return row
    drone = build_drone(drone_cfg, cache_dir, sim_cfg.element)
    r = dcfg.record
    record_flights(drone, sim_cfg, noise_cfg, folder / "logs", int(r.flights), float(r.seconds), list(r.manoeuvres),
                   int(sc["seed"]), float(r.height), float(r.ground), float(r.amplitude), effects=sc["effects"])
    rep = run_workflow(drone, drone_cfg, sim_cfg, noise_cfg, dcfg, folder / "logs", folder / "workflow", cache_dir,
                       seed=int(sc["seed"]), plots=False, log=lambda *a: None)
    named = [e["name"] for e in rep["effects"]]
    top1 = named[0] if named else rep["verdict"]
    row = {"id": sc["id"], "kind": sc["kind"], "truth": "+".join(sc["truth"]) or "none",
           "verdict": rep["verdict"], "top1": top1, "named": "+".join(named), "ties": "+".join(rep["ties"]),
           "gap_before": rep["gap"]["gap_before"], "gap_after": rep["gap"]["gap_after"],
           "gap_reduction": rep["gap"]["reduction"], "held_loss_before": rep["gap"]["held_loss_before"],
           "held_loss_after": rep["gap"]["held_loss_after"], "rollouts": rep["rollouts"],
           "seconds": time.perf_counter() - t0, "true_effects": json.dumps(sc["effects"]),
           "fitted": json.dumps(rep["effects"])}
    row.update(param_fit(sc, rep))
    row.update(oracle_gap(sc, folder, drone, drone_cfg, sim_cfg, noise_cfg, dcfg, cache_dir))
    if key is not None:
        atomic_write(folder / ROW_FILE, lambda tmp: tmp.write_text(json.dumps({"key": key, "row": row})))
    return row


ROW_FILE = "row.json"


def scenario_key(sc: dict, drone_cfg, sim_cfg, noise_cfg, dcfg) -> str | None:
    """What makes a scenario's row: the scenario, the configs and the code's commit. None (never
    reused) where the code has uncommitted changes or no commit to name: a row is only as good
    as the code that made it."""
    from sdexp.cache import config_key, key_of
    from sdexp.provenance import source
    code = source()
    if "commit" not in code or "uncommitted" in code:
        return None
    return key_of("bench-scenario", 1, {"scenario": sc, "code": code, "drone": config_key(drone_cfg),
                                        "sim": config_key(sim_cfg), "noise": config_key(noise_cfg),
                                        "discrepancy": config_key(dcfg)})


def finished_row(folder: Path, key: str | None) -> dict | None:
    """The row a finished scenario wrote under ``key``, or None (not finished, made otherwise, damaged)."""
    try:
        done = json.loads((Path(folder) / ROW_FILE).read_text())
    except (OSError, ValueError):
        return None
    return done.get("row") if key is not None and done.get("key") == key else None


def oracle_gap(sc: dict, folder: Path, drone, drone_cfg, sim_cfg, noise_cfg, dcfg, cache_dir: str) -> dict:
    """The gap the workflow closed, measured against the one it could close: held-out loss of
    the nominal simulator, of the fitted one and of the simulator with the true (hidden)
    effects, on the workflow's held-out windows. reduction = (nominal - fitted) / (nominal -
    true), capped at 1. (The workflow's own gap is against the noise floor of other flights,
    which differs from flight set to flight set by more than a moderate effect's gap.)"""
    from sdexp.discrepancy.fit import window_loss
    from sdexp.discrepancy.localize import noise_floor
    from sdexp.discrepancy.logs import read_logs
    from sdexp.discrepancy.windows import Predictor, make_windows, subset
    from sdexp.discrepancy.workflow import history_of, prepare, split_flights, steps_of, trimmed

    folder = Path(folder)
    logs = read_logs(folder / "logs", drone.name, drone.num_rotors, drone.layout.n_s, drone.dim)
    h, stride, hist = steps_of(dcfg, logs.dt, history_of(drone, dcfg))
    w = make_windows(logs.flights, logs.channels, h, stride, hist, int(dcfg.start_average))
    _, held_ids = split_flights(len(logs.flights), dcfg.holdout)
    held = subset(w, held_ids)
    bend, r_floor, _, bend_for = prepare(drone, drone_cfg, sim_cfg, noise_cfg, dcfg, cache_dir)
    sigma = noise_floor(r_floor)
    pred = Predictor(drone, sim_cfg, noise_cfg, bend, bend_for)
    fitted = list(yaml.safe_load((folder / "workflow" / "sim_fitted.yaml").read_text()).get("effects") or [])
    loss = lambda eff: trimmed(window_loss(pred.residual(held, eff), sigma))
    L_nom = loss([])
    L_fit = loss(fitted) if fitted else L_nom
    L_true = loss(sc["effects"]) if sc["effects"] else L_nom
    closable = L_nom - L_true
    return {"oracle_loss_nominal": L_nom, "oracle_loss_fitted": L_fit, "oracle_loss_true": L_true,
            "oracle_gap_reduction": float(min(1.0, (L_nom - L_fit) / closable)) if closable > 0 else None}


def param_fit(sc: dict, rep: dict) -> dict:
    """The strength parameter of the first true effect, when it was named: its relative error,
    and whether the fit's interval covers the truth (a vector: every component; the wrong rotor
    of a thrust loss: no)."""
    out = {"param_error": None, "param_covered": None}
    if sc["kind"] not in ("single", "combo") or not rep["effects"]:
        return out
    truth = sc["effects"][0]
    fitted = next((e for e in rep["effects"] if e["name"] == truth["name"]), None)
    if fitted is None:
        return out
    key = LIBRARY[truth["name"]].bench_strengths[0]
    p = fitted["params"]
    if truth["name"] == "thrust_loss" and p.get("rotor") != truth["rotor"]:
        return {"param_error": 1.0, "param_covered": False}
    t, f = np.asarray(truth[key], float), np.asarray(p[key], float)
    out["param_error"] = float(np.linalg.norm(f - t) / np.linalg.norm(t))   # |.| for a scalar
    interval = (fitted.get("params_interval") or {}).get(key)
    if interval is not None:
        lo, hi = (np.asarray(b, float) for b in interval)
        out["param_covered"] = bool(np.all((lo <= t) & (t <= hi)))
    return out


def rescore_row(row: dict, drone_cfg, sim_cfg, noise_cfg, dcfg, scen_dir: str, cache_dir: str, report=None) -> dict:
    """oracle_gap for a scenario already run (a row of scenarios.csv and its folder); a failed
    one has nothing to score."""
    from sdexp.sim.drone import build_drone
    out = row
    if row["verdict"] != FAILED:
        drone = build_drone(drone_cfg, cache_dir, sim_cfg.element)
        sc = {"effects": json.loads(row["true_effects"])}
        out = {**row, **oracle_gap(sc, Path(scen_dir) / row["id"], drone, drone_cfg, sim_cfg, noise_cfg, dcfg,
                                   cache_dir)}
    if report:
        report(1)
    return out


def summarize(table: pd.DataFrame) -> dict:
    """The bench's figures over the scenarios that ran; those that failed are listed with why
    (``failed_scenarios``), not scored."""
    table = table.copy()
    for col in ("named", "ties", "top1", "truth", "verdict"):   # empty cells read back as NaN
        table[col] = table[col].fillna("").astype(str)
    failed = {r.get("id"): r.get("error") for r in table[table.verdict == FAILED].to_dict("records")}
    head = {"scenarios": int(len(table)), "scenarios_failed": len(failed), "failed_scenarios": failed}
    table = table[table.verdict != FAILED]
    if table.empty:
        return {**head, "targets_met": {}}
    single = table[table.kind == "single"]
    out = {**head, **_answers(table), **_gaps(table[table.kind.isin(["single", "combo"])])}
    out.update({
        "scenario_seconds_median": float(np.median(table.seconds)) if "seconds" in table else None,
        "scenario_seconds_total": float(np.sum(table.seconds)) if "seconds" in table else None,
        "median_param_error": float(np.nanmedian(single.param_error.astype(float))) if single.param_error.notna().any() else None,
        # how often the named effect's 95% interval holds its true strength (a bench run before the
        # intervals existed has no such column: None)
        "param_interval_coverage": _share(single.get("param_covered")),
        "per_effect_param_interval_coverage": {n: _share(g.get("param_covered")) for n, g in single.groupby("truth")
                                               if _share(g.get("param_covered")) is not None},
        "per_effect_top1": {n: float(np.mean(g.top1 == n)) for n, g in single.groupby("truth")},
    })
    out["targets_met"] = _targets(out)
    return out


def detectable(table: pd.DataFrame) -> pd.Series:
    """Whether each scenario's hidden effects show in its held-out flights at all: the true
    effects cut the nominal simulator's held-out loss by at least 5% (the workflow's min_gain),
    or, where a replay of the truth cannot reproduce them (random gusts: the replay flies the
    mean wind), the nominal loss is at least twice the noise floor's (gap_before >= 1). A bench
    from before the oracle columns: every scenario."""
    if "oracle_loss_nominal" not in table:
        return pd.Series(True, index=table.index)
    nom, true = table.oracle_loss_nominal.astype(float), table.oracle_loss_true.astype(float)
    return ((nom - true) >= 0.05 * nom) | (table.gap_before.astype(float) >= 1.0)


def _answers(table: pd.DataFrame) -> dict:
    """What the workflow answered, per scenario kind: the library effects, the nulls, the
    combinations, the effects outside the library and their variants. The targets count the
    scenarios whose effect is ``detectable``; the figures over all of them stand beside."""
    seen = detectable(table)
    single = table[table.kind == "single"]
    null = table[table.kind == "null"]
    combo = table[table.kind == "combo"]
    unmod = table[table.kind == "unmodelled"]
    variant = table[table.kind == "variant"]
    answered = table[table.kind.isin(["single", "variant"])]
    truthful = table[table.kind.isin(["single", "variant", "combo"])]
    return {
        "top1_accuracy": _top1(single),
        "top1_or_tie_accuracy": float(np.mean([t == s or t in ties.split("+") for t, s, ties in
                                               zip(single.truth, single.top1, single.ties)])) if len(single) else None,
        "null_false_positive_rate": float(np.mean(null.verdict != "none")) if len(null) else None,
        "combo_first_in_truth": float(np.mean([a in t.split("+") for a, t in zip(combo.top1, combo.truth)]))
        if len(combo) else None,
        "combo_both_found": float(np.mean([set(n.split("+")) == set(t.split("+")) for n, t in
                                           zip(combo.named, combo.truth)])) if len(combo) else None,
        "unmodelled_answered_unexplained": float(np.mean(unmod.verdict == "unexplained")) if len(unmod) else None,
        # a real effect missed silently: no effect named and nothing reported above the floor
        "unmodelled_answered_none": float(np.mean(unmod.verdict == "none")) if len(unmod) else None,
        "variant_fair_answer": float(np.mean(variant.top1 == variant.truth)) if len(variant) else None,
        # every effect with a library answer: the library's own and the variants (gusty wind, ...)
        "top1_with_library_answer": _top1(answered),
        "top1_accuracy_detectable": _top1(single[seen[single.index]]),
        "top1_with_library_answer_detectable": _top1(answered[seen[answered.index]]),
        "undetectable_scenarios": sorted(table.id[~seen & (table.kind != "null")]) if "id" in table else [],
        # over the outside effects the flights show (detectable), as the issue counts; all beside
        "unmodelled_honest": _honest(unmod[seen[unmod.index]]),
        "unmodelled_honest_all": _honest(unmod),
        # a named effect after the first that is not among the truth's, over every scenario with a
        # library truth (a wrong first answer is a top-1 miss, not counted here)
        "spurious_second_effect_rate": float(np.mean([bool(set(n.split("+")[1:]) - set(t.split("+")))
                                                      for n, t in zip(truthful.named, truthful.truth)]))
        if len(truthful) else None,
        "per_effect_param_error": {n: float(np.nanmedian(g.param_error.astype(float)))
                                   for n, g in single.groupby("truth") if g.param_error.notna().any()},
        "per_variant_answer": dict(zip(variant.id, variant.named)) if len(variant) else {},
        "per_unmodelled_answer": dict(zip(unmod.id, unmod.verdict + ":" + unmod.named)) if len(unmod) else {},
    }


def _top1(rows: pd.DataFrame) -> float | None:
    return float(np.mean(rows.top1 == rows.truth)) if len(rows) else None


def _honest(unmod: pd.DataFrame) -> float | None:
    """An outside effect answered honestly: unexplained, partly (named effects and the rest
    unexplained), or named effects that close >= 80% of the gap its true effect closes."""
    if not len(unmod):
        return None
    gaps = unmod.get("oracle_gap_reduction", pd.Series([None] * len(unmod), index=unmod.index))
    return float(np.mean([v in ("unexplained", "partly") or (g is not None and g == g and g >= 0.8)
                          for v, g in zip(unmod.verdict, gaps)]))


def _gaps(effect: pd.DataFrame) -> dict:
    """How much of the held-out gap the named effects close, over the scenarios with an effect."""
    red = effect.gap_reduction.fillna(0.0).clip(upper=1.0)
    oracle = effect.oracle_gap_reduction if "oracle_gap_reduction" in effect else pd.Series(dtype=float)
    # a gap counts when the true effects cut the nominal held-out loss by >= 5% (the workflow's
    # min_gain): below that the hidden effect is not visible in these flights at all
    if "oracle_loss_nominal" in effect:
        measurable = (effect.oracle_loss_nominal - effect.oracle_loss_true) >= 0.05 * effect.oracle_loss_nominal
    else:
        measurable = oracle.notna()
    return {
        "median_gap_reduction_vs_floor": float(np.median(red)) if len(red) else None,
        # against the gap the true effects close (scenarios where they close any), unnamed = 0
        "median_gap_reduction": float(np.median(oracle[measurable].clip(lower=-1.0))) if measurable.any() else None,
        "gap_measurable_scenarios": int(measurable.sum()),
        "mean_gap_reduction": float(np.mean(oracle[measurable].clip(lower=-1.0))) if measurable.any() else None,
    }


def _targets(out: dict) -> dict:
    """The issue's targets, met or not."""
    def at_least(key, v):
        return out[key] is not None and out[key] >= v
    return {
        "top1_accuracy_detectable>=0.95": at_least("top1_accuracy_detectable", 0.95),
        "top1_with_library_answer_detectable>=0.95": at_least("top1_with_library_answer_detectable", 0.95),
        "spurious_second_effect_rate<=0.05": out["spurious_second_effect_rate"] is not None
        and out["spurious_second_effect_rate"] <= 0.05,
        "unmodelled_honest>=0.8": at_least("unmodelled_honest", 0.8),
        "null_false_positive_rate<=0.05": out["null_false_positive_rate"] is not None and out["null_false_positive_rate"] <= 0.05,
        "median_gap_reduction>=0.8": at_least("median_gap_reduction", 0.8),
        "param_interval_coverage>=0.8": at_least("param_interval_coverage", 0.8),
    }


def _share(flags) -> float | None:
    """The share of True among the scored entries (None, NaN and empty cells are not scored)."""
    if flags is None:
        return None
    scored = [bool(v) if not isinstance(v, str) else v == "True" for v in flags if v is not None and v == v and v != ""]
    return float(np.mean(scored)) if scored else None


def confusion(table: pd.DataFrame) -> pd.DataFrame:
    t = table[table.kind.isin(["single", "null", "variant", "unmodelled"])]
    return pd.crosstab(t.truth, t.top1).rename_axis(index="truth", columns="named")


def confusion_plot(cm: pd.DataFrame, path) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(1.2 + 0.45 * cm.shape[1], 1.2 + 0.4 * cm.shape[0]))
    ax.imshow(cm.to_numpy(), cmap="Blues")
    ax.set_xticks(range(cm.shape[1]), cm.columns, rotation=90, fontsize=7)
    ax.set_yticks(range(cm.shape[0]), cm.index, fontsize=7)
    for (i, j), v in np.ndenumerate(cm.to_numpy()):
        if v:
            ax.text(j, i, str(v), ha="center", va="center", fontsize=7)
    ax.set_xlabel("workflow's answer (top-1)")
    ax.set_ylabel("hidden effect")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


NEEDS_3D = ("rotor_reaction_torque",)   # a 2D rotor has no spin axis


def effect_names(params, dim: int) -> list[str]:
    """The library effects the bench hides: experiment.params.effects, or where null those of the
    library a ``dim``-D drone has."""
    names = list(params.effects or LIBRARY)
    flat = [n for n in names if n in NEEDS_3D]
    if dim == 2 and flat and params.effects:
        raise UserError(f"experiment.params.effects = {names!r}: {flat[0]} needs a 3D drone: allowed on this 2D "
                        f"drone {', '.join(n for n in LIBRARY if n not in NEEDS_3D)}")
    return [n for n in names if dim == 3 or n not in NEEDS_3D]


def bench_scenarios(drone, params, seed: int) -> list[dict]:
    """The scenarios experiment.params asks for (``only``: those of them it names)."""
    scs = scenarios(drone, effect_names(params, drone.dim), int(params.seeds), int(params.nulls), bool(params.combos),
                    int(params.unmodelled), seed, tuple(params.levels or (0, 1)), int(params.variants))
    return select(scs, params.only)


def scenario_folder(params, out_dir: Path) -> Path:
    """Where each scenario's logs and workflow outputs go (~1.5 MB each): experiment.params.scenario_dir
    (outside a results folder), else <run dir>/scenarios."""
    return Path(str(params.scenario_dir)).expanduser() if params.scenario_dir else Path(out_dir) / "scenarios"


def check(params, out_dir: Path, drone_cfg, sim_cfg, cache_dir: str, seed: int) -> None:
    """The bench's parameters that the folders and the drone must allow, in one pass before
    anything is written (their types, ranges and names are the params' own checks,
    sdexp.experiment_params): the effects on this drone, the scenario folder, an earlier run to
    rescore, the scenarios ``only`` names (the drone is built for those only)."""
    effect_names(params, int(drone_cfg.dim))
    scen_dir = scenario_folder(params, out_dir)
    if params.scenario_dir:   # the run folder's own is the run's to check (sdexp.eval.run)
        _check_folder("experiment.params.scenario_dir", params.scenario_dir, scen_dir)
    if params.rescore:
        _check_rescore(Path(out_dir), scen_dir)
    elif params.only:
        from sdexp.sim.drone import build_drone
        bench_scenarios(build_drone(drone_cfg, cache_dir, sim_cfg.element), params, seed)


def _check_folder(key: str, value, path: Path) -> None:
    """``path`` is a folder, or can be made as one: its nearest existing parent is a writable folder."""
    there = next(p for p in (path, *path.parents) if p.exists())
    if not there.is_dir():
        raise UserError(f"{key} = {value!r}: {there} is a file: allowed a folder (made if missing), or null "
                        "for <run dir>/scenarios")
    if not os.access(there, os.W_OK | os.X_OK):
        raise UserError(f"{key} = {value!r}: {there} is not writable: allowed a folder this user can write, or "
                        "null for <run dir>/scenarios")


RESCORED = ("id", "verdict", "true_effects")   # the columns of scenarios.csv that rescoring reads


def _check_rescore(out_dir: Path, scen_dir: Path) -> None:
    """experiment.params.rescore: the run folder holds an earlier bench's scenarios.csv, and the
    scenario folder each of its rows that ran (its logs and fitted simulator)."""
    table = out_dir / "scenarios.csv"
    where = ("allowed only in the folder of an earlier bench run (hydra.run.dir=<its folder>, its metrics.json "
             "and config.yaml deleted), with experiment.params.scenario_dir where its scenario folders are")
    try:
        old = pd.read_csv(table, keep_default_na=False, na_values=[""])
    except FileNotFoundError:
        raise UserError(f"experiment.params.rescore = true: {table} does not exist: {where}") from None
    except (OSError, ValueError) as err:
        raise UserError(f"experiment.params.rescore = true: {table} cannot be read ({one_line(err)}): {where}") from None
    missing = [c for c in RESCORED if c not in old]
    if missing:
        raise UserError(f"experiment.params.rescore = true: {table} has no column {missing[0]!r}: {where}")
    for sid in old.id[old.verdict != FAILED]:
        for need in (scen_dir / str(sid) / "logs", scen_dir / str(sid) / "workflow" / "sim_fitted.yaml"):
            if not need.exists():
                raise UserError(f"experiment.params.rescore = true: scenario {sid}'s {need} does not exist: "
                                f"{where}")


def run_bench(drone_cfg, sim_cfg, noise_cfg, dcfg, params, out_dir: Path, cache_dir: str, seed: int = 0,
              workers: int = 2, progress=None) -> dict:
    from sdexp.discrepancy.workflow import prepare
    from sdexp.parallel import run_spawned
    from sdexp.sim.drone import build_drone

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    drone = build_drone(drone_cfg, cache_dir, sim_cfg.element)
    scs = bench_scenarios(drone, params, seed)
    prepare(drone, drone_cfg, sim_cfg, noise_cfg, dcfg, cache_dir)   # cache it once for every worker
    args = [drone_cfg, sim_cfg, noise_cfg, dcfg]   # what the spawned workers need, and nothing of the root config
    scen_dir = str(scenario_folder(params, out_dir))
    if params.rescore:
        # re-score the scenarios of an earlier run (its scenarios.csv and folders) with this code
        old = pd.read_csv(out_dir / "scenarios.csv", keep_default_na=False, na_values=[""]).to_dict("records")
        fn, tasks = rescore_row, [(r, *args, scen_dir, cache_dir) for r in old]
    else:
        fn, tasks = run_scenario, [(sc, *args, scen_dir, cache_dir) for sc in scs]
        resumed = sum(finished_row(Path(scen_dir) / sc["id"], scenario_key(sc, *args)) is not None for sc in scs)
        if resumed:
            log.info(f"discrepancy_bench: {resumed} of {len(scs)} scenarios finished in {scen_dir} "
                     "by a run of this code and config: read, not run again")
    if workers > 1:
        rows = run_spawned(fn, tasks, workers, progress)
    else:
        rows = [fn(*t, report=progress) for t in tasks]
    table = pd.DataFrame(rows)
    atomic_write(out_dir / "scenarios.csv", lambda tmp: table.to_csv(tmp, index=False))
    cm = confusion(table)
    atomic_write(out_dir / "confusion.csv", lambda tmp: cm.to_csv(tmp))
    confusion_plot(cm, out_dir / "confusion.png")
    metrics = summarize(table)
    if metrics["scenarios_failed"]:
        log.warning(f"discrepancy_bench: {metrics['scenarios_failed']} of {len(table)} scenarios failed, "
                    f"not scored: {metrics['failed_scenarios']}")
    metrics["wall_seconds"] = time.perf_counter() - t0
    metrics["workers"] = workers
    metrics["scenarios_resumed"] = 0 if params.rescore else resumed
    metrics["targets_met"]["wall_minutes<=30"] = metrics["wall_seconds"] <= 30 * 60
    return metrics
