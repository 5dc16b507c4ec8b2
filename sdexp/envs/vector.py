"""Many environments on every core: Gymnasium's AsyncVectorEnv with one sub-env per process, each
simulator on one thread (two one-thread processes share 2 cores better than threads do:
sdexp.parallel)."""
from __future__ import annotations

from collections.abc import Mapping


def one_thread(overrides=None):
    """``overrides`` (a list of ``key=value`` or a mapping, as SoftDroneEnv takes them) with the
    simulator on one thread, unless they set ``sim.threads`` themselves."""
    if isinstance(overrides, Mapping):
        return {"sim.threads": 1, **overrides}
    if isinstance(overrides, str):
        return overrides   # refused by name where the env reads it
    return ["sim.threads=1", *(overrides or [])]   # Hydra: the later of two settings of a key wins


def make_vec(env_id: str, num_envs: int | None = None, overrides=None, **kw):
    """``num_envs`` sub-envs of ``env_id`` stepping side by side in as many processes (default:
    one per core this process may use, sdexp.parallel.available_cores); the keywords are
    gymnasium.make's (``seconds=5``, ``action_scale=...``). The processes are spawned, not forked
    (numba, torch and OpenMP state stay out of them): a script that calls this needs the
    ``if __name__ == "__main__":`` guard."""
    import gymnasium as gym

    from sdexp.errors import UserError
    from sdexp.parallel import available_cores, one_thread_children

    cores = available_cores()
    num_envs = cores if num_envs is None else num_envs
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise UserError(f"num_envs = {num_envs!r} is out of range: allowed an integer >= 1 "
                        f"(default {cores}: the cores this process may use)")
    with one_thread_children():
        return gym.make_vec(env_id, num_envs, vectorization_mode="async", vector_kwargs={"context": "spawn"},
                            overrides=one_thread(overrides), **kw)
