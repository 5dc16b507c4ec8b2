"""Statistics over a sweep's jobs: plain functions behind ``sdexp experiment=report``.

A sweep folder (``sdexp -m ...``'s multirun folder, or any folder of finished runs) holds one
folder per job with its ``metrics.json`` and ``config.yaml``. Jobs are grouped by the config
values that differ between them, the seed (and where a run looks things up) aside: a sweep over
``control.n x seed`` gives one group per n. Per group and metric:

* a number: n (its finite values), mean, sample standard deviation and the two-sided Student-t
  confidence interval ``mean +- t(1 - alpha/2, n - 1) s / sqrt(n)`` (none for n = 1);
* a boolean (``ours_survived``): how many jobs it was true in, e.g. "survived 5 of 5".

Strings (a failure's reason) and lists are not aggregated.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.errors import UserError
from sdexp.eval.run import NOT_COMPARED

# not what tells a group from another: the seed, and what a rerun does not compare either
IGNORED_KEYS = ("seed", *NOT_COMPARED)


def _flat(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: node}


def find_jobs(sweep_dir: str | Path, own: Path | None = None) -> list[Path]:
    """The job folders under ``sweep_dir`` (itself included) that hold a metrics.json, in name
    order; report runs and hidden folders (submitit's .submitit) are not jobs. A missing folder,
    a file, a folder without any metrics.json, or one with an unfinished job (a job folder, with
    its config.yaml or log, but no metrics.json: still running, killed or failed) is a UserError
    naming it: statistics over the finished jobs only would read as the whole sweep's. ``own``:
    the report's own run folder, when it lies inside the sweep (Hydra made it, with its log)."""
    root = Path(sweep_dir).expanduser()
    shown = root.resolve() if root.exists() else root.absolute()
    if not root.exists():
        raise UserError(f"sweep folder {shown} does not exist: give a multirun folder with "
                        f"sweep_dir=<folder> (sdexp -m ... writes multirun/<experiment>/<time>)")
    if not root.is_dir():
        raise UserError(f"sweep folder {shown} is not a folder: give a multirun folder with sweep_dir=<folder>")
    jobs, unfinished = [], []
    for folder in sorted({p.parent for pattern in ("metrics.json", "config.yaml", "*.log")
                          for p in root.rglob(pattern)}):
        if any(part.startswith(".") for part in folder.relative_to(root).parts):
            continue
        if experiment_of(folder) == "report" or (own is not None and folder.resolve() == own.resolve()):
            continue
        (jobs if (folder / "metrics.json").exists() else unfinished).append(folder)
    if unfinished:
        names = ", ".join(str(f.relative_to(root)) for f in unfinished[:5])
        more = f" and {len(unfinished) - 5} more" if len(unfinished) > 5 else ""
        raise UserError(f"sweep folder {shown} has {len(unfinished)} unfinished job{'s' if len(unfinished) > 1 else ''} "
                        f"(no metrics.json): {names}{more}; finish {'them' if len(unfinished) > 1 else 'it'} "
                        f"(rerun the sweep's command: finished jobs skip) or remove {'their folders' if len(unfinished) > 1 else 'its folder'}")
    if not jobs:
        raise UserError(f"sweep folder {shown} holds no finished job (no metrics.json under it): give the "
                        f"folder of a sweep whose jobs have finished with sweep_dir=<folder>")
    return jobs


def experiment_of(folder: Path) -> str | None:
    """The experiment a run folder's config.yaml names (None where it cannot be read)."""
    try:
        from omegaconf import OmegaConf
        return OmegaConf.select(OmegaConf.load(folder / "config.yaml"), "experiment.name")
    except Exception:   # noqa: BLE001 - read (and reported) properly by load_job
        return None


def load_job(folder: Path) -> tuple[dict, dict]:
    """(flat resolved config, flat metrics) of one job folder."""
    from omegaconf import OmegaConf
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError) as err:
        raise UserError(f"{folder / 'metrics.json'} cannot be read ({err}): rerun that job or remove it "
                        f"from the sweep folder") from None
    if not isinstance(metrics, dict):
        raise UserError(f"{folder / 'metrics.json'} is not a mapping of metrics: rerun that job")
    path = folder / "config.yaml"
    try:
        config = OmegaConf.to_container(OmegaConf.load(path))
    except FileNotFoundError:
        raise UserError(f"{path} is missing: a job folder needs the config it ran (sdexp writes it) to "
                        f"be grouped; rerun that job or remove it from the sweep folder") from None
    except Exception as err:   # noqa: BLE001 - a damaged file
        raise UserError(f"{path} cannot be read ({err}): rerun that job or remove it") from None
    return _flat(config), _flat(metrics)


def _text(value) -> str:
    if isinstance(value, float) and value.is_integer():
        return str(int(value)) if abs(value) < 1e15 else repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_text(v) for v in value) + "]"
    return str(value)


def group_jobs(configs: list[dict]) -> tuple[list[str], list[tuple[str, ...]]]:
    """(the config keys that differ between jobs, the seed and IGNORED_KEYS aside; each job's
    values of them as text): jobs with equal values form one group."""
    keys = sorted(set().union(*configs)) if configs else []
    varying = [k for k in keys if k not in IGNORED_KEYS
               and len({_text(c.get(k, "<absent>")) for c in configs}) > 1]
    return varying, [tuple(_text(c.get(k, "<absent>")) for k in varying) for c in configs]


def short_names(keys: list[str]) -> list[str]:
    """Dotted keys by their last part where that is unambiguous (control.n -> n)."""
    last = [k.rsplit(".", 1)[-1] for k in keys]
    return [s if last.count(s) == 1 else k for k, s in zip(keys, last)]


def interval(values, confidence: float = 0.95) -> dict:
    """n, mean, standard deviation and the Student-t interval of the finite ``values``."""
    from scipy import stats
    x = np.asarray([v for v in values if v is not None], dtype=float)
    x = x[np.isfinite(x)]
    n = len(x)
    if n == 0:
        return {"n": 0, "mean": math.nan, "std": math.nan, "ci_low": math.nan, "ci_high": math.nan}
    mean = float(x.mean())
    if n == 1:
        return {"n": 1, "mean": mean, "std": math.nan, "ci_low": math.nan, "ci_high": math.nan}
    std = float(x.std(ddof=1))
    half = float(stats.t.ppf(0.5 + confidence / 2, n - 1)) * std / math.sqrt(n)
    return {"n": n, "mean": mean, "std": std, "ci_low": mean - half, "ci_high": mean + half}


def count_text(metric: str, true: int, n: int) -> str:
    if metric == "survived" or metric.endswith("_survived"):
        who = metric[: -len("_survived")] if metric.endswith("_survived") else ""
        return f"{who + ' ' if who else ''}survived {true} of {n}"
    return f"{metric} true in {true} of {n}"


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def aggregate(sweep_dir: str | Path, confidence: float = 0.95, own: Path | None = None) -> pd.DataFrame:
    """One row per (group, metric): the group's config values (a column per dotted key), kind (number | count), n, mean,
    std, ci_low, ci_high, true (counts), summary and the method in words."""
    loaded, varying, groups = grouped_jobs(sweep_dir, own)
    pct = f"{confidence:.0%}"
    t_method = f"Student t {pct}: mean +- t({0.5 + confidence / 2:g}, n-1) * s / sqrt(n), s the sample std"
    rows = []
    for (label, gvals), members in groups.items():
        seeds = sorted({loaded[i][0].get("seed") for i in members}, key=str)
        metrics = []
        for i in members:
            metrics += [m for m in loaded[i][1] if m not in metrics]
        for m in metrics:
            vals = [loaded[i][1][m] for i in members if m in loaded[i][1]]
            row = {"group": label, **dict(zip(varying, gvals)), "metric": m, "jobs": len(members),
                   "seeds": " ".join(map(str, seeds))}
            if vals and all(isinstance(v, bool) for v in vals):
                true = int(sum(vals))
                rows.append({**row, "kind": "count", "n": len(vals), "mean": true / len(vals), "std": math.nan,
                             "ci_low": math.nan, "ci_high": math.nan, "true": true,
                             "summary": count_text(m, true, len(vals)),
                             "method": "count of jobs where it is true (mean: their fraction)"})
            elif vals and all(_is_number(v) or v is None for v in vals):
                s = interval(vals, confidence)
                if s["n"] >= 2:
                    text = f"{s['mean']:.4g} [{s['ci_low']:.4g}, {s['ci_high']:.4g}] (n={s['n']})"
                else:
                    text = f"{s['mean']:.4g} (n={s['n']}, no interval)"
                rows.append({**row, "kind": "number", **s, "true": None, "summary": text,
                             "method": t_method})
    columns = ["group", *varying, "metric", "kind", "jobs", "seeds", "n", "mean", "std", "ci_low", "ci_high",
               "true", "summary", "method"]
    return pd.DataFrame(rows, columns=columns)


def grouped_jobs(sweep_dir: str | Path, own: Path | None = None) -> tuple[list, list[str], dict]:
    """(every finished job's (flat config, flat metrics), the varying keys, {(label, values): job
    indices}) in the groups' numeric order; a label reads "q_s=100, n=5" (the experiment's name
    when nothing varies but the seed)."""
    loaded = [load_job(f) for f in find_jobs(sweep_dir, own)]
    varying, values = group_jobs([c for c, _ in loaded])
    names = short_names(varying)
    members: dict[tuple, list[int]] = {}
    for i, v in enumerate(values):
        members.setdefault(v, []).append(i)
    groups = {}
    for gvals, idx in sorted(members.items(), key=lambda kv: _sort_key(kv[0])):
        label = ", ".join(f"{n}={v}" for n, v in zip(names, gvals)) or str(loaded[idx[0]][0].get("experiment.name", "all"))
        groups[(label, gvals)] = idx
    return loaded, varying, groups


def _sort_key(values: tuple) -> tuple:
    """Groups in numeric order where the values are numbers (n=5 before n=10)."""
    out = []
    for v in values:
        try:
            out.append((0, float(v), ""))
        except ValueError:
            out.append((1, 0.0, v))
    return tuple(out)


# ------------------------------------------------------------------------------ the plot

def metric_groups(metrics: list[str], min_share: int = 3) -> dict[str, list[tuple[str, str]]]:
    """Metrics by the quantity they measure: ``ours_final_error`` and ``rigid_lqr_final_error``
    are the final error of two controllers. A metric's prefix ("who": ours, rigid_lqr, n5) is its
    longest underscore prefix that starts at least ``min_share`` metrics (else 2); the rest is
    the quantity. Returns quantity -> [(who, metric)], who being '' for a metric without one."""
    tokens = {m: m.split("_") for m in metrics}
    starts: dict[str, int] = {}
    for t in tokens.values():
        for i in range(1, len(t)):
            starts["_".join(t[:i])] = starts.get("_".join(t[:i]), 0) + 1
    out: dict[str, list[tuple[str, str]]] = {}
    for m, t in tokens.items():
        who = ""
        for share in (min_share, 2):   # a prefix of few metrics (n5_final_error, n5_survival_time) at last
            for i in range(1, len(t)):
                if starts["_".join(t[:i])] >= share:
                    who = "_".join(t[:i])
            if who:
                break
        quantity = m[len(who) + 1:] if who else m
        out.setdefault(quantity, []).append((who, m))
    return out


def plot(table: pd.DataFrame, path: Path, title: str = "", max_panels: int = 24) -> None:
    """One panel per metric group (numbers only): each group of jobs' mean with its confidence
    interval as error bars, one series per controller / prefix."""
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    nums = table[table["kind"] == "number"]
    quantities = metric_groups(list(dict.fromkeys(nums["metric"])))
    panels = list(quantities.items())[:max_panels]
    groups = list(dict.fromkeys(table["group"]))
    if not panels:
        fig, ax = plt.subplots(figsize=(5, 2))
        ax.text(0.5, 0.5, "no numeric metrics", ha="center", va="center")
        ax.set_axis_off()
        save_figure(fig, path, dpi=120)
        return
    cols = min(3, len(panels))
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.6 * rows), squeeze=False)
    for ax, (quantity, members) in zip(axes.ravel(), panels):
        whos = [w for w, _ in members]
        one_group = len(groups) == 1
        for k, (who, metric) in enumerate(members):
            rows_m = nums[nums["metric"] == metric].set_index("group").reindex(groups)
            mean = rows_m["mean"].to_numpy(float)
            err = np.vstack([mean - rows_m["ci_low"].to_numpy(float), rows_m["ci_high"].to_numpy(float) - mean])
            err = np.where(np.isfinite(err), err, 0.0)
            if one_group:
                x = np.array([k], float)
            else:
                x = np.arange(len(groups)) + (k - (len(members) - 1) / 2) * 0.8 / max(len(members), 1)
            ax.errorbar(x, mean, yerr=err, fmt="o", capsize=4, label=who or metric)
        if one_group:
            ax.set_xticks(range(len(members)))
            ax.set_xticklabels([w or m for w, m in members], rotation=20, ha="right")
        else:
            ax.set_xticks(range(len(groups)))
            ax.set_xticklabels(groups, rotation=20, ha="right")
            if any(whos):
                ax.legend(fontsize=8)
        ax.set_title(quantity, fontsize=11)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(panels):]:
        ax.set_axis_off()
    n = int(nums["n"].max()) if len(nums) else 0
    method = nums["method"].iloc[0].split(":")[0] if len(nums) else ""
    fig.suptitle(f"{title}  (mean and {method} interval, up to n = {n} jobs per point)".strip(), fontsize=12)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def check_metrics(loaded: list, names: list[str], sweep_dir) -> None:
    """Every metric of ``names`` is some job's (``loaded``: grouped_jobs' first), else a UserError
    listing the numeric and boolean metrics the jobs have."""
    have = sorted({m for _, met in loaded for m, v in met.items() if _is_number(v) or isinstance(v, bool)})
    for metric in names:
        if metric not in have:
            raise UserError(f"experiment.params.scatter: no job of {sweep_dir} has the metric {metric!r}; "
                            f"its numeric and boolean metrics: {', '.join(have)}")


def scatter(sweep_dir: str | Path, axes: list[str], path: Path, lines: list | None = None,
            own: Path | None = None, title: str = "") -> int:
    """One point per job: metric ``axes[0]`` against ``axes[1]``, a colour per group; with a third,
    boolean metric (e.g. ``passed``) a point is filled where it is true, hollow where not. ``lines``:
    reference values drawn dashed at x = lines[0] and y = lines[1] (None: none), e.g. a paper's
    figures. A frontier (what one figure costs of another over the settings tried) reads at a
    glance. Returns the points drawn; a metric no job has is a UserError listing those that exist."""
    from sdexp.figures import pyplot, save_figure
    loaded, _, groups = grouped_jobs(sweep_dir, own)
    check_metrics(loaded, axes, sweep_dir)
    x_name, y_name, mark = (list(axes) + [None])[:3]
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    drawn = 0
    for k, ((label, _), idx) in enumerate(groups.items()):
        colour = f"C{k % 10}"
        for i in idx:
            met = loaded[i][1]
            if not (_is_number(met.get(x_name)) and _is_number(met.get(y_name))):
                continue
            filled = mark is None or bool(met.get(mark))
            ax.scatter(met[x_name], met[y_name], s=46, edgecolors=colour, linewidths=1.5,
                       facecolors=colour if filled else "none")
            drawn += 1
        ax.scatter([], [], s=46, color=colour, label=label)   # the legend's marker: the colour alone
    for value, draw in zip(lines or [], (ax.axvline, ax.axhline)):
        if value is not None:
            draw(float(value), color="0.4", ls="--", lw=1)
    ax.set_xlabel(x_name)
    ax.set_ylabel(y_name)
    ax.grid(alpha=0.3)
    if len(groups) > 1:
        ax.legend(fontsize=8, title="filled: " + mark if mark else None, title_fontsize=8)
    elif mark:
        ax.set_title(f"filled: {mark}", fontsize=9)
    fig.suptitle(f"{title}: one point per job".strip(": "), fontsize=11)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    return drawn
