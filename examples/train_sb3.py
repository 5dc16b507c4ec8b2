"""Train a Stable-Baselines3 agent on a soft drone and compare it with ours (Algorithm 1) in the
same environment.

    pip install -e ".[rl]"
    python examples/train_sb3.py                          # PPO on sdexp/Rod-Hover-v0, 20k steps
    python examples/train_sb3.py --steps 200000 --env sdexp/Engine-Reach-v0 --compare-ours

The rod is the cheapest drone (96 quadratic triangles, about 1000 env steps/s on one core:
``python -m sdexp.envs.bench``). The env is used as it is registered: actions in [-1, 1] (x Tmax),
bounded observations. SB3 prints its progress table after every rollout (``--verbose 0``: quiet).
``--compare-ours`` identifies the rod's learned dynamics as every
sdexp experiment does (cached in $SDEXP_CACHE; cold it generates data and trains d, g, h: minutes)
and evaluates ours over the same episodes. Extra ``--override key=value`` arguments go to the
sdexp config (e.g. ``--override noise.enabled=false``).
"""
from __future__ import annotations

import argparse
import logging

import gymnasium as gym

import sdexp.envs  # noqa: F401 - registers the sdexp/ environments

log = logging.getLogger("train_sb3")


def make_env(env_id: str, overrides: list[str], seconds: float | None):
    """The env as registered, in SB3's Monitor (episode returns as they were)."""
    from stable_baselines3.common.monitor import Monitor
    kw = {} if seconds is None else {"seconds": seconds}
    return Monitor(gym.make(env_id, overrides=overrides, **kw))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="sdexp/Rod-Hover-v0")
    ap.add_argument("--steps", type=int, default=20_000, help="training budget in env steps")
    ap.add_argument("--seconds", type=float, default=5.0, help="episode length (the task's duration)")
    ap.add_argument("--episodes", type=int, default=3, help="evaluation episodes")
    ap.add_argument("--n-steps", type=int, default=1024, help="PPO's rollout length")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--override", action="append", default=[], help="sdexp config override key=value")
    ap.add_argument("--compare-ours", action="store_true", help="also evaluate ours in the same env")
    ap.add_argument("--verbose", type=int, default=1, help="SB3's verbosity: 1 a progress table per rollout")
    args = ap.parse_args(argv)
    from stable_baselines3 import PPO
    from stable_baselines3.common.evaluation import evaluate_policy

    env = make_env(args.env, args.override, args.seconds)
    agent = PPO("MlpPolicy", env, n_steps=min(args.n_steps, args.steps), batch_size=64, seed=args.seed,
                verbose=args.verbose)
    log.info(f"PPO on {args.env}: {args.steps:,} steps, a rollout of {agent.n_steps} then its update")
    agent.learn(total_timesteps=args.steps)
    mean, std = evaluate_policy(agent, env, n_eval_episodes=args.episodes, deterministic=True)
    result = {"env": args.env, "steps": args.steps, "ppo_return": float(mean), "ppo_return_std": float(std)}
    log.info(f"PPO after {args.steps} steps: return {mean:.1f} +- {std:.1f} over {args.episodes} episodes "
             f"(at most {args.seconds / env.unwrapped.dt:.0f}: 1 per step on the goal)")
    if args.compare_ours:
        from sdexp.envs.policy import OursPolicy
        mean, std = evaluate_policy(OursPolicy(env), env, n_eval_episodes=args.episodes)
        result.update(ours_return=float(mean), ours_return_std=float(std))
        log.info(f"ours: return {mean:.1f} +- {std:.1f}")
    return result


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main()
