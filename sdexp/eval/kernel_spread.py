"""``sdexp experiment=kernel_spread``: how far the fleet's outcomes move with the last bits of the
BLAS libraries (issue 52, item 4).

numpy's OpenBLAS and torch's MKL pick their kernels by CPU and round otherwise, so the same
command learns slightly different data and nets on another machine; a controller whose verdict
hangs on those bits is a draw, not a result. This runs one fleet per kernel choice of
``kernels`` (names of ``sdexp.experiment_params.KERNELS``: the environment of each process, e.g.
``OPENBLAS_CORETYPE=Haswell``, ``MKL_CBWR=AVX2``), each a fresh ``sdexp experiment=fleet <overrides>`` process with its own cache, so its
data and nets are made afresh under those kernels (the cache is keyed on the config, not on the
kernels: a shared one would hand the first kernel's data to all). What the BLAS libraries do not
make is shared from the run's cache (``shared``: the meshes, the body's statics and the compiled
simulator, made by the mesher and the C kernels), so each fleet pays only for what is measured.

Writes ``kernel_spread.csv`` (one row per kernel choice and fleet flight, with the OpenBLAS
kernel each process actually ran: a name OpenBLAS does not know falls back silently),
``kernel_spread.png`` (each flight's error over its tolerance, one column of points per kernel
choice) and metrics: per drone, task and controller the kernel choices within tolerance and the
spread (least and largest error). The fleets' folders stay under ``fleets/<kernel>`` (each resumes
on its own); ``fleets/<kernel>.log`` is each process's output.
"""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd

from sdexp.eval.run import Run

log = logging.getLogger(__name__)

# one core a fleet: the kernel choices run side by side
ONE_CORE = ["sim.threads=1", "data.workers=1", "model.threads=1", "experiment.params.workers=1"]
_PROBE = ("import json, numpy, threadpoolctl; print(json.dumps([i.get('architecture') for i in "
          "threadpoolctl.threadpool_info() if i.get('internal_api') == 'openblas']))")


def check(run: Run) -> None:
    """The fleet's overrides compose (a typo is named before any fleet starts)."""
    from sdexp.eval.run import compose_overrides, preflight, typed

    cfg = compose_overrides(["experiment=fleet", *ONE_CORE, *run.params.overrides],
                            f"experiment.params.overrides = {list(run.params.overrides)!r}")
    preflight(cfg)
    typed(cfg)


def fleet_command(cache_dir: Path, run_dir: Path, overrides: list[str]) -> list[str]:
    return [sys.executable, "-m", "sdexp.cli", "experiment=fleet", f"cache_dir={cache_dir}",
            f"hydra.run.dir={run_dir}", *ONE_CORE, *overrides]


def share_cache(source: Path, target: Path, kinds: list[str]) -> int:
    """Link ``source``'s cache entries of ``kinds`` into ``target`` (made if missing); returns how
    many. The entries are read, never written, by the fleet that finds them."""
    target.mkdir(parents=True, exist_ok=True)
    linked = 0
    for entry in source.iterdir() if source.is_dir() else ():
        if entry.name.split("-")[0] in kinds and not (target / entry.name).exists():
            (target / entry.name).symlink_to(entry.resolve())
            linked += 1
    return linked


def fly_kernel(name: str, env: dict, out_dir: Path, cache: Path, p) -> dict:
    """One kernel choice's fleet, in its own process and cache; the OpenBLAS kernel it ran."""
    run_dir, kernel_cache = out_dir / "fleets" / name, out_dir / "caches" / name
    linked = share_cache(cache, kernel_cache, list(p.shared))
    child_env = {**os.environ, **{k: str(v) for k, v in env.items()}, "SDEXP_CACHE": str(kernel_cache)}
    probe = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env=child_env)
    arch = ", ".join(json.loads(probe.stdout or "[]") or ["?"]) if probe.returncode == 0 else "?"
    log.info(f"sdexp: kernel_spread: {name} ({', '.join(f'{k}={v}' for k, v in env.items()) or 'as the machine picks'}; "
             f"OpenBLAS {arch}), {linked} cache entries shared -> {run_dir}")
    t0 = time.perf_counter()
    with open(out_dir / "fleets" / f"{name}.log", "a") as out:
        res = subprocess.run(fleet_command(kernel_cache, run_dir, list(p.overrides)), stdout=out,
                             stderr=subprocess.STDOUT, env=child_env)
    return {"kernel": name, "env": env, "openblas": arch, "returncode": res.returncode,
            "seconds": time.perf_counter() - t0, "run_dir": run_dir}


def run(run: Run) -> dict:
    from sdexp.log import Phase

    p, out_dir = run.params, run.out_dir
    (out_dir / "fleets").mkdir(parents=True, exist_ok=True)
    cache = Path(str(run.cfg.cache_dir)).expanduser()
    from sdexp.experiment_params import KERNELS
    kernels = {name: KERNELS[name] for name in p.kernels}
    with Phase("kernel choices (a fleet each)", total=len(kernels), unit="fleets") as bar, \
            ThreadPoolExecutor(max_workers=max(1, min(int(p.workers), len(kernels)))) as pool:
        futures = [pool.submit(fly_kernel, name, env, out_dir, cache, p) for name, env in kernels.items()]
        done = []
        for f in futures:
            done.append(f.result())
            bar.update(1)
    failed = [d for d in done if d["returncode"] != 0 or not (d["run_dir"] / "fleet.csv").exists()]
    if failed:
        log.warning("sdexp: kernel_spread: no fleet table from " + ", ".join(
            f"{d['kernel']} (exit {d['returncode']}: fleets/{d['kernel']}.log)" for d in failed))
    frames = []
    for d in done:
        if d not in failed:
            t = pd.read_csv(d["run_dir"] / "fleet.csv")
            frames.append(t.assign(kernel=d["kernel"], openblas=d["openblas"], fleet_seconds=d["seconds"]))
    if not frames:
        raise RuntimeError("no kernel choice's fleet finished: see fleets/<kernel>.log")
    table = pd.concat(frames, ignore_index=True)
    table = table[table["outcome"] != "beyond the body"]
    run.table(table, "kernel_spread")
    plot(table, list(kernels), out_dir / "kernel_spread.png")
    out = metrics(table)
    out.update(kernels=len(kernels), kernels_failed=len(failed))
    return out


def metrics(table: pd.DataFrame) -> dict:
    """Per drone, seed, task and controller: the kernel choices within tolerance, of how many, and
    the least and largest error (its unit the task's)."""
    out = {}
    for (drone, seed, task, ctl), grp in table.groupby(["drone", "seed", "task", "controller"]):
        name = f"{drone}_seed{seed}_{task}_{ctl}"
        out[f"{name}_within"] = int((grp["outcome"] == "within").sum())
        out[f"{name}_kernels"] = len(grp)
        values = grp["primary_value"].where(grp["survived"].astype(bool))
        out[f"{name}_min"] = float(values.min()) if values.notna().any() else float("nan")
        out[f"{name}_max"] = float(values.max()) if values.notna().all() else float("inf")
    return out


def plot(table: pd.DataFrame, kernels: list[str], path: Path) -> None:
    """Per flight (drone, seed, task, controller) a row, per kernel choice a point: its error over
    the task's tolerance (1 = on the line), a cross where control was lost."""
    import matplotlib.pyplot as plt

    from sdexp.figures import save_figure
    flights = table.groupby(["drone", "seed", "task", "controller"], sort=True)
    fig, ax = plt.subplots(figsize=(8, 0.45 * flights.ngroups + 1.6))
    for row, (key, grp) in enumerate(flights):
        for _, r in grp.iterrows():
            x = kernels.index(r["kernel"])
            lost = not bool(r["survived"])
            ratio = 30.0 if lost else float(r["primary_value"]) / float(r["tolerance"])
            ax.scatter(x, row, c="tab:red" if lost or ratio > 1 else "tab:green", marker="x" if lost else "o",
                       s=25 + 20 * min(ratio, 3))
            if not lost:
                ax.annotate(f"{ratio:.2g}", (x, row), textcoords="offset points", xytext=(6, -3), fontsize=7)
    ax.set_yticks(range(flights.ngroups), [" ".join(map(str, k)) for k, _ in flights], fontsize=8)
    ax.set_xticks(range(len(kernels)), kernels, rotation=30, fontsize=8)
    ax.set_title("error / tolerance per BLAS kernel choice (green within, red missed, x lost)", fontsize=10)
    ax.invert_yaxis()
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def summary(params, metrics: dict) -> str:
    lines = []
    for key in sorted(k for k in metrics if k.endswith("_within")):
        name = key[: -len("_within")]
        lines.append(f"  {name}: {metrics[key]} of {metrics[name + '_kernels']} kernel choices within, "
                     f"error {metrics[name + '_min']:.3g} to {metrics[name + '_max']:.3g}")
    return "\n".join(lines)
