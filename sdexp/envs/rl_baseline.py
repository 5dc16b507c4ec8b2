"""``sdexp experiment=rl_baseline``: a model-free baseline beside the paper's method at equal data.

The question a learning researcher asks first: how many environment transitions does model-free
RL need for the flight ours makes from its 60,000? A Stable-Baselines3 agent (SAC by default:
off-policy, the sample-efficient choice; PPO by option) trains in the drone's Gymnasium
environment (``SoftDroneEnv``: the same decomposed IMU state as ours' observation, the paper's
sensor and rotor noise and 30 ms output delay, actions in [-1, 1] x Tmax) on each task of
``tasks``, one training run per task and seed, saved at every budget of ``budgets``. Every
checkpoint and ours are then scored on the same seeded episodes of the same environment.

**Where each learns and where it is judged.** Both learn on ``data.sim_model`` (the reduced-order
model by default: ours' training transitions are made there, the agent trains there) and both are
scored on ``sim.model`` (the full FEM): equal data from one world, judged in another, so neither
is scored on the simulator it learned from. ``data.sim_model=null`` learns on the full model too
(about 10x slower per transition).

**Scored** per episode: survived (no loss of control, blow-up or controller failure), the final
distance to the goal and whether it is within the fleet's tolerance (``sdexp.eval.fleet.tolerance``:
hover 0.1 m; reach 10% of the trip), the return, and the training's wall time to that budget
(ours': identification, data and nets, 0 where the cache held them), in CPU seconds of the job's
process: one core each, so its wall time on an idle core, whatever else shares the machine.

Jobs (``jobs/``): one per task and seed for the agent (its checkpoints ``<task>_seed<s>_<algo>/
<budget>.zip`` and its scores, ``<task>_seed<s>_<algo>.json``) and one per seed for ours; a
finished job is kept when the run resumes (keyed on what makes it); a training killed midway
starts again. Writes ``rl_baseline.csv`` (one row per episode), ``rl_baseline.png`` (final error
against transitions) and metrics (per task: episodes within tolerance and the median final
error, per budget and for ours).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.errors import UserError
from sdexp.eval.fleet import job_progress, write_job
from sdexp.eval.run import Run

log = logging.getLogger(__name__)

EPISODE_SEED = 1000   # the scored episodes of seed s: reset(seed=EPISODE_SEED * (s + 1) + episode)
REPORTS = 20          # progress lines per training run


def check(run: Run) -> None:
    """Stable-Baselines3 is the rl extra's: without it the run stops before anything is written."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        raise UserError("experiment=rl_baseline trains a Stable-Baselines3 agent: install the rl extra "
                        "(pip install -e \".[rl]\")") from None


def _algorithm(name: str):
    from stable_baselines3 import PPO, SAC
    return {"sac": SAC, "ppo": PPO}[name]


def _configs(cfg, seed: int):
    """(where it learns, where it is scored): the run's config at ``seed``, on one core (the jobs run
    side by side), the first on ``data.sim_model``."""
    scored = replace(cfg, seed=int(seed), sim=replace(cfg.sim, threads=1), data=replace(cfg.data, workers=1),
                     model=replace(cfg.model, threads=1))
    learn = replace(scored, sim=replace(scored.sim, model=cfg.data.sim_model or cfg.sim.model))
    return learn, scored


def _env(cfg, task: str):
    from sdexp.envs.env import SoftDroneEnv
    return SoftDroneEnv(config=cfg, task=task)


def _trip(env) -> float:
    return float(np.linalg.norm(env.task.target - env.task.start))


def score(env, act, seed: int, episodes: int, reset=None) -> list[dict]:
    """``episodes`` seeded episodes of ``env`` under ``act(obs) -> action`` (``reset()`` after each
    env reset: a controller's own state)."""
    from sdexp.eval.fleet import FleetParams, tolerance
    tol = tolerance(env.task_name, FleetParams(), _trip(env))
    rows = []
    for k in range(episodes):
        obs, info = env.reset(seed=EPISODE_SEED * (int(seed) + 1) + k)
        if reset is not None:
            reset()
        ret, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(act(obs))
            ret += reward
            done = terminated or truncated
        survived = not terminated
        rows.append({"episode": k, "survived": bool(survived), "failure": info["failure"],
                     "survival_time": float(info["t"]), "final_error": float(info["position_error"]),
                     "tolerance": tol, "within": bool(survived and info["position_error"] <= tol),
                     "return": float(ret)})
    return rows


def _checkpoints(jobs_dir: Path, task: str, seed: int, algo: str) -> Path:
    return jobs_dir / f"{task}_seed{seed}_{algo}"


def train_agent(cfg, task: str, seed: int, p, jobs_dir: str, key: str, report=None) -> dict:
    """One agent: trained on ``task`` to the largest budget, saved at each, every checkpoint scored."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.monitor import Monitor

    from sdexp.files import atomic_write

    torch.set_num_threads(1)   # one core a job: the jobs run side by side
    learn_cfg, scored_cfg = _configs(cfg, seed)
    budgets = sorted(int(b) for b in p.budgets)
    folder = _checkpoints(Path(jobs_dir), task, seed, p.algorithm)
    folder.mkdir(parents=True, exist_ok=True)
    name = f"{task} seed {seed}: {p.algorithm}"
    cpu: dict[int, float] = {}   # CPU seconds of training at each budget

    class Checkpoints(BaseCallback):
        def _on_training_start(self) -> None:
            self.t0 = time.process_time()

        def _on_step(self) -> bool:
            n = self.num_timesteps
            if n in budgets:
                cpu[n] = time.process_time() - self.t0
                path = folder / f"{n}.zip"
                atomic_write(path, self.model.save)   # its temporary name has a suffix: SB3 adds none
            if report is not None and n % max(1, budgets[-1] // REPORTS) == 0:
                report(f"{name} {n:,} of {budgets[-1]:,} transitions")
            return True

    env = Monitor(_env(learn_cfg, task))
    algo = _algorithm(p.algorithm)
    agent = algo("MlpPolicy", env, seed=int(seed), device="cpu", verbose=0)
    t0 = time.process_time()
    agent.learn(total_timesteps=budgets[-1], callback=Checkpoints())
    train_seconds = time.process_time() - t0
    env.close()

    scored = _env(scored_cfg, task)
    rows = []
    for n in budgets:
        if report is not None:
            report(f"{name} scoring the {n:,}-transition agent on {scored_cfg.sim.model}")
        policy = algo.load(folder / f"{n}.zip", device="cpu")
        act = lambda obs: policy.predict(obs, deterministic=True)[0]
        rows += [{"task": task, "seed": int(seed), "controller": p.algorithm, "transitions": n,
                  "train_seconds": cpu[n], **r} for r in score(scored, act, seed, int(p.episodes))]
    result = {"key": key, "rows": rows, "train_seconds": train_seconds,
              "steps_per_second": budgets[-1] / train_seconds}
    write_job(Path(jobs_dir) / f"{task}_seed{seed}_{p.algorithm}.json", result)
    if report is not None:
        report(1)
    return result


def fly_ours(cfg, seed: int, p, jobs_dir: str, key: str, report=None) -> dict:
    """Ours at ``seed``: identified (its data on data.sim_model), then scored on every task."""
    from sdexp.envs.policy import OursPolicy

    _, scored_cfg = _configs(cfg, seed)
    rows, identify_seconds = [], None
    for task in p.tasks:
        env = _env(scored_cfg, task)
        if report is not None:
            report(f"ours seed {seed}: {task}" + (" (identifying: data and nets)" if identify_seconds is None else ""))
        t0 = time.process_time()
        policy = OursPolicy(env, progress=False)
        identify_seconds = time.process_time() - t0 if identify_seconds is None else identify_seconds
        rows += [{"task": task, "seed": int(seed), "controller": "ours", "transitions": int(cfg.data.samples),
                  "train_seconds": identify_seconds, **r}
                 for r in score(env, policy, seed, int(p.episodes), reset=policy.reset)]
    result = {"key": key, "rows": rows, "train_seconds": identify_seconds}
    write_job(Path(jobs_dir) / f"ours_seed{seed}.json", result)
    if report is not None:
        report(1)
    return result


def _done(path: Path, key: str) -> dict | None:
    try:
        done = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return done if done.get("key") == key else None


def _key(cfg, p, what: str, seed: int) -> str:
    """What makes a job's result: the config (less the run's folder, cores and cache) and, for the
    agent, the algorithm, budgets and episodes; for ours, the tasks and episodes."""
    from sdexp.cache import config_key, key_of
    job = {f.name: config_key(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)
           if f.name not in ("cache_dir", "cores", "sweep_dir", "experiment", "seed")}
    params = {"episodes": int(p.episodes), "seed": int(seed)}
    if what == "ours":
        params["tasks"] = list(p.tasks)
    else:
        params.update(task=what, algorithm=p.algorithm, budgets=sorted(int(b) for b in p.budgets))
    return key_of("rl-baseline-job", 1, {"job": job, "params": params})


def run(run: Run) -> dict:
    from sdexp.log import Phase
    from sdexp.parallel import run_spawned

    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    jobs_dir = out_dir / "jobs"
    jobs_dir.mkdir(exist_ok=True)
    done, todo = [], []
    # the agents first: each trains for minutes to hours; ours' jobs fill the other core
    for seed in p.seeds:
        for task in p.tasks:
            key = _key(cfg, p, task, seed)
            found = _done(jobs_dir / f"{task}_seed{seed}_{p.algorithm}.json", key)
            (done.append(found) if found else todo.append((train_agent, (cfg, task, seed, p, str(jobs_dir), key))))
    for seed in p.seeds:
        key = _key(cfg, p, "ours", seed)
        found = _done(jobs_dir / f"ours_seed{seed}.json", key)
        (done.append(found) if found else todo.append((fly_ours, (cfg, seed, p, str(jobs_dir), key))))
    log.info(f"sdexp: rl_baseline: {cfg.drone.name}, {p.algorithm} at {', '.join(f'{b:,}' for b in sorted(p.budgets))} "
             f"transitions and ours at its {cfg.data.samples:,}, learned on the "
             f"{cfg.data.sim_model or cfg.sim.model} model, scored on the {cfg.sim.model} one; "
             f"{len(done)} of {len(done) + len(todo)} jobs done before")
    t0 = time.perf_counter()
    with Phase("rl_baseline jobs (agents, ours)", total=len(todo), unit="jobs") as bar:
        report = job_progress(bar)   # the fleet's: a phase shown, a job done counted
        workers = max(1, min(int(p.workers), len(todo)))
        if workers == 1:
            done += [fn(*args, report=report) for fn, args in todo]
        else:
            done += run_spawned(_call, todo, workers, report)
    table = pd.DataFrame([r for job in done for r in job["rows"]])
    table = table.sort_values(["task", "controller", "transitions", "seed", "episode"]).reset_index(drop=True)
    run.table(table, "rl_baseline")
    plot(table, p, out_dir / "rl_baseline.png", f"{cfg.drone.name}: {p.algorithm} against ours, learned on the "
         f"{cfg.data.sim_model or cfg.sim.model} model, scored on the {cfg.sim.model} one")
    out = metrics(table, p)
    agents = [job for job in done if "steps_per_second" in job]
    if agents:
        out[f"{p.algorithm}_steps_per_second_median"] = float(np.median([j["steps_per_second"] for j in agents]))
    out["wall_seconds_this_invocation"] = time.perf_counter() - t0
    return out


def _call(fn, args, report=None):
    """run_spawned's task: a job function and its arguments."""
    return fn(*args, report=report)


def metrics(table: pd.DataFrame, p) -> dict:
    """Per task, for ours and for the agent at each budget: episodes, within tolerance, survived,
    the median final error and the median training seconds."""
    out = {}
    for (task, ctl, n), grp in table.groupby(["task", "controller", "transitions"]):
        name = f"{task}_ours" if ctl == "ours" else f"{task}_{ctl}_{n}"
        out.update({f"{name}_transitions": int(n), f"{name}_episodes": len(grp),
                    f"{name}_within": int(grp["within"].sum()), f"{name}_survived": int(grp["survived"].sum()),
                    f"{name}_final_error_median": float(grp["final_error"].median()),
                    f"{name}_train_seconds_median": float(grp["train_seconds"].median())})
    return out


def plot(table: pd.DataFrame, p, path: Path, title: str) -> None:
    """Per task: the final distance to the goal against the transitions learned from, every
    episode a point (a cross where the flight was lost), the agent's median a line, ours a star;
    the tolerance dashed."""
    import matplotlib.pyplot as plt

    from sdexp.figures import save_figure
    tasks = list(p.tasks)
    fig, axes = plt.subplots(1, len(tasks), figsize=(5.5 * len(tasks), 4.2), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        rows = table[table["task"] == task]
        for ctl, colour, marker in ((p.algorithm, "tab:blue", "o"), ("ours", "tab:red", "*")):
            mine = rows[rows["controller"] == ctl]
            for lost, m in ((False, marker), (True, "x")):
                part = mine[mine["survived"] != lost]
                ax.scatter(part["transitions"], part["final_error"], c=colour, marker=m, s=60 if m == "*" else 25,
                           alpha=0.7, label=f"{ctl}{' (lost)' if lost else ''}" if len(part) else None)
            med = mine.groupby("transitions")["final_error"].median()
            if ctl != "ours" and len(med):
                ax.plot(med.index, med.values, c=colour, lw=1.5)
            within = int(mine["within"].sum())
            ax.plot([], [], " ", label=f"{ctl}: {within} of {len(mine)} within")
        tol = float(rows["tolerance"].iloc[0]) if len(rows) else np.nan
        ax.axhline(tol, ls="--", c="k", lw=1, label=f"tolerance {tol:.2g} m")
        ax.set(xscale="log", yscale="log", xlabel="environment transitions learned from",
               ylabel="final distance to the goal (m)", title=task)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    save_figure(fig, path, dpi=110)


def summary(params, metrics: dict) -> str:
    lines = []
    for task in params.tasks:
        parts = [f"ours ({metrics.get(f'{task}_ours_transitions', 0):,}) {metrics.get(f'{task}_ours_within', 0)} of "
                 f"{metrics.get(f'{task}_ours_episodes', 0)} within, median {metrics.get(f'{task}_ours_final_error_median', np.nan):.3g} m"]
        for n in sorted(params.budgets):
            name = f"{task}_{params.algorithm}_{n}"
            parts.append(f"{params.algorithm} ({n:,}) {metrics.get(f'{name}_within', 0)} of {metrics.get(f'{name}_episodes', 0)} "
                         f"within, median {metrics.get(f'{name}_final_error_median', np.nan):.3g} m")
        lines.append(f"  {task}: " + "; ".join(parts))
    return "\n".join(lines)
