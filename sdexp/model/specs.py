"""The networks of Eq. 4 by what they read and predict, in the dataset's arrays
(sdexp.model.dataset): the trainer builds each network's design from its spec
(sdexp.model.training), LearnedDynamics places its output in the state (sdexp.model.dynamics).

    d(s, s_dot, u)                      -> s_dot_next
    g(s, s_dot, e, e_dot, u)            -> e_dot_next
    h(s, s_dot, e, e_dot, p_dot, u)     -> p_dot_next
    raw(raw, raw_dot, u)                -> raw_dot_next     (decomposition ablation only)
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class NetSpec:
    name: str
    inputs: tuple[str, ...]   # dataset keys, concatenated in this order
    target: str               # dataset key of the next-frame velocity
    current: str              # dataset key of its current value (one of the inputs)


DECOMPOSED = (
    NetSpec("d", ("s", "s_dot", "u"), "s_dot_next", "s_dot"),
    NetSpec("g", ("s", "s_dot", "e", "e_dot", "u"), "e_dot_next", "e_dot"),
    NetSpec("h", ("s", "s_dot", "e", "e_dot", "p_dot", "u"), "p_dot_next", "p_dot"),
)
UNDECOMPOSED = (NetSpec("raw", ("raw", "raw_dot", "u"), "raw_dot_next", "raw_dot"),)
