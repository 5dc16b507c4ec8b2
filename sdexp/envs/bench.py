"""Environment steps per second on one core (one env, one simulator thread) and on two (two envs
in two processes, sdexp.envs.make_vec), random thrusts, episodes restarted as they end.

    python -m sdexp.envs.bench                      # rod, engine and flower hover, 2000 steps each
    python -m sdexp.envs.bench --drones rod --steps 500

Timings depend on the machine and its load: read them, never assert them.
"""
from __future__ import annotations

import argparse
import logging
import time

import numpy as np

log = logging.getLogger(__name__)


def one_core(env_id: str, steps: int, overrides=(), seed: int = 0) -> float:
    import gymnasium as gym

    from sdexp.envs.vector import one_thread
    env = gym.make(env_id, overrides=one_thread(overrides))   # a second simulator thread would take the other core
    env.reset(seed=seed)
    env.action_space.seed(seed)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


def two_cores(env_id: str, steps: int, overrides=(), seed: int = 0) -> float:
    """Steps of both envs together per second (``steps`` each)."""
    from sdexp.envs.vector import make_vec
    envs = make_vec(env_id, 2, overrides=overrides)
    envs.reset(seed=seed)
    envs.action_space.seed(seed)
    t0 = time.perf_counter()
    for _ in range(steps):   # sub-envs restart by themselves (autoreset)
        envs.step(envs.action_space.sample())
    rate = 2 * steps / (time.perf_counter() - t0)
    envs.close()
    return rate


def bench(drones=("rod", "engine", "flower"), task: str = "hover", steps: int = 2000, overrides=()) -> list[dict]:
    import sdexp.envs
    rows = []
    for drone in drones:
        env_id = sdexp.envs.env_id(drone, task)
        one, two = one_core(env_id, steps, overrides), two_cores(env_id, steps, overrides)
        rows.append({"env": env_id, "steps_per_s_1_core": one, "steps_per_s_2_cores": two,
                     "real_time_1_core": one * 0.01})   # control steps are 10 ms (sim.control_dt)
        log.info(f"{env_id}: {one:,.0f} steps/s on 1 core ({one * 0.01:.1f}x real time), "
                 f"{two:,.0f} steps/s on 2 cores (2 envs, {two / one:.2f}x)")
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description="Gymnasium env steps per second on 1 and 2 cores")
    ap.add_argument("--drones", nargs="+", default=["rod", "engine", "flower"])
    ap.add_argument("--task", default="hover")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--override", action="append", default=[], help="sdexp config override key=value")
    args = ap.parse_args(argv)
    return bench(args.drones, args.task, args.steps, args.override)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main()
