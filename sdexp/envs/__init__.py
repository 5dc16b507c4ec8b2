"""The soft drones as Gymnasium environments: ``import sdexp.envs`` registers
``sdexp/<Drone>-<Task>-v0`` for every drone of sdexp/conf/drone and every task of
sdexp.envs.tasks (``sdexp/Rod-Hover-v0``, ``sdexp/Flower-Reach-v0``, ...)::

    import gymnasium, sdexp.envs
    env = gymnasium.make("sdexp/Rod-Reach-v0", seconds=5, overrides={"noise.enabled": False})
    envs = sdexp.envs.make_vec("sdexp/Rod-Reach-v0")     # one env per core, each in its process

The environment is sdexp.envs.env.SoftDroneEnv; ours (Algorithm 1) acts in it as
sdexp.envs.policy.OursPolicy."""
from __future__ import annotations

import gymnasium as gym

from sdexp import conf
from sdexp.envs.tasks import TASKS
from sdexp.envs.vector import make_vec  # noqa: F401 - the API: sdexp.envs.make_vec

NAMESPACE = "sdexp"
VERSION = 0


def env_id(drone: str, task: str) -> str:
    """``sdexp/OrangePeel-Hover-v0`` for drone orange_peel, task hover."""
    camel = "".join(part.capitalize() for part in drone.split("_"))
    return f"{NAMESPACE}/{camel}-{task.capitalize()}-v{VERSION}"


def env_ids() -> dict[str, tuple[str, str]]:
    """Every registered id -> (drone, task)."""
    return {env_id(d, t): (d, t) for d in conf.paper_drones() for t in TASKS}


def register() -> None:
    for name, (drone, task) in env_ids().items():
        if name not in gym.registry:
            # no max_episode_steps: the env truncates at its task's duration, which keywords change
            gym.register(id=name, entry_point="sdexp.envs.env:SoftDroneEnv",
                         kwargs={"drone": drone, "task": task})


register()
