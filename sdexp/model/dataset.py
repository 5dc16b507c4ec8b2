"""Training data for the learned dynamics (supplement F) -- INTERFACE STUB, being implemented.

A dataset is a set of transitions, one per 10 ms control step, computed from sensor readings
only (noise and delay as configured):

  keys (arrays of float32, first axis N transitions):
    s, s_dot        (N, n_s)   bend angles and rates           (sdexp.sim.sensors.State)
    e, e_dot        (N, n_e)   Euler angles and rates (n_e = 3 in 3D, 1 in 2D)
    p, p_dot        (N, dim)   position and velocity
    u               (N, m)     the commanded thrusts held during the step
    s_dot_next, e_dot_next, p_dot_next   the rates read one control step later
    raw, raw_dot, raw_dot_next (N, n_raw)  the undecomposed state for the decomposition
                    ablation: concat(p, central IMU Euler angles, every peripheral IMU's
                    world-frame Euler angles (2D: angle)) and its rates
    episode         (N,) int32 episode index; t (N,) float32 time in the episode
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KEYS = ("s", "s_dot", "e", "e_dot", "p", "p_dot", "u", "s_dot_next", "e_dot_next", "p_dot_next",
        "raw", "raw_dot", "raw_dot_next", "episode", "t")


@dataclass
class Dataset:
    arrays: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)  # drone, dim, n_s, n_e, m, control_dt, samples/s

    def __len__(self) -> int:
        return len(self.arrays["u"])

    def split(self, validation_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(train, validation) transition indices, split by whole episodes."""
        raise NotImplementedError


def load_dataset(cfg) -> Dataset:
    """The dataset for cfg.drone / cfg.sim / cfg.noise / cfg.data / cfg.seed, from the cache
    or generated (both cores, progress bar, atomic and resumable)."""
    raise NotImplementedError
