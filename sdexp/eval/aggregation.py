"""On-policy data aggregation (``data.aggregation``; issue 52): data where the drone flies.

The paper's data are random thrust holds from rest (supplement F); the states ours flies through
(level, near hover, moving toward a goal) are a small part of them (the leaf: 13% of its data
within 0.2 rad of level). The paper also reports that data from a guiding controller alone fails
to train ("the confined distribution of LQR control outputs"), so the rounds here add to the
random holds, never replace them (DAgger's aggregation, Ross et al. 2011): after the nets are
trained on the holds, ``rounds`` times ours flies ``flights`` flights of ``seconds`` from rest to
goals drawn uniformly within ``reach`` body lengths of its release; their transitions, read from
the IMUs exactly as the data's (noise, delay; sdexp.model.generate.episode), join the data and
the nets are trained again on all of it.

A round's flights are cached (keyed by the data and nets they were flown with, the control,
world and aggregation configs, the seed and the round), as are the nets (keyed by the data's
content). A flight that fails ends its transitions there (the failing step is dropped, as in the
data); a round whose flights all fail before adding a transition is logged with its reasons, and
the rounds go on with the data they have."""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import replace

import numpy as np

from sdexp.cache import cached_arrays, config_key, key_of

log = logging.getLogger(__name__)

FORMAT = 1   # bump when a round's flights or their transitions change


def aggregate(cfg, data, trained, dyn, progress: bool = True, priors: dict | None = None):
    """(dataset, trained nets, LearnedDynamics) after ``cfg.data.aggregation.rounds`` rounds from
    the identified ones (``priors``: the nets', model.prior)."""
    from sdexp.model.identification import identify_on

    agg = cfg.data.aggregation
    for r in range(1, int(agg.rounds) + 1):
        flown, ends = round_transitions(cfg, data, trained, dyn, r)
        got, how = len(flown["u"]), ", ".join(f"{k} {v}" for k, v in sorted(ends.items()))
        log.info(f"sdexp: data aggregation round {r} of {agg.rounds}: {agg.flights} flights of ours, "
                 f"{got} transitions added to {len(data)} ({how})")
        if got == 0:
            log.warning(f"sdexp: data aggregation round {r}: every flight failed before its first transition "
                        f"({', '.join(sorted(ends))}); the round adds nothing, the next flies the same nets")
            continue
        data = data.joined(flown, f"round {r} ({how})")
        trained, dyn = identify_on(cfg, data, progress, priors)
    return data, trained, dyn


def round_transitions(cfg, data, trained, dyn, round_: int) -> tuple[dict, Counter]:
    """The transitions of one round's flights (arrays keyed as the data's) and how they ended."""
    agg = cfg.data.aggregation
    key = key_of("aggregation", FORMAT, {
        "data": arrays_key_of(data), "nets": trained.key, "control": config_key(cfg.control),
        "model": config_key(cfg.model), "drone": config_key(cfg.drone), "sim": config_key(replace(cfg.sim, obstacles=[])),
        "noise": config_key(cfg.noise), "aggregation": config_key(agg), "region": float(cfg.data.region),
        "seed": int(cfg.seed), "round": int(round_)})
    made = cached_arrays(cfg.cache_dir, key, lambda: _fly_round(cfg, data, trained, dyn, round_))
    ends = Counter({str(k): int(v) for k, v in zip(made.pop("end_names"), made.pop("end_counts"))})
    return made, ends


def arrays_key_of(data) -> str:
    """The data's content (its arrays), as the nets' key reads it."""
    from sdexp.model.training import dataset_key
    return dataset_key(data, sorted(data.arrays))


class _Ended(Exception):
    """A flight of a round ends before its time (its reason)."""


def _fly_round(cfg, data, trained, dyn, round_: int) -> dict:
    from sdexp.control.lqr import LqrFailure
    from sdexp.control.rollout import LossOfControl
    from sdexp.control.tasks import Task
    from sdexp.eval.controllers import build
    from sdexp.sim.drone import drone_length
    from sdexp.model.generate import Rows, episode, widths
    from sdexp.sim.drone import build_drone
    from sdexp.sim.simulator import Simulator

    agg = cfg.data.aggregation
    sim_cfg = replace(cfg.sim, obstacles=[], threads=1)
    drone = build_drone(cfg.drone, cfg.cache_dir, sim_cfg.element)
    lay = drone.layout
    dt = float(sim_cfg.control_dt)
    steps = max(1, int(round(float(agg.seconds) / dt)))
    rows = Rows(int(agg.flights) * steps, widths(lay.dim, lay.n_s, drone.num_rotors), None)
    length = drone_length(cfg.drone, drone)
    ends: Counter = Counter()
    sim = Simulator(drone, sim_cfg, cfg.noise, seed=0)
    for flight in range(int(agg.flights)):
        ss_goal, ss_noise = np.random.SeedSequence(int(cfg.seed), spawn_key=(1_000_000 + round_, flight)).spawn(2)
        goal_rng = np.random.default_rng(ss_goal)
        offset = goal_rng.normal(size=lay.dim)
        offset *= float(agg.reach) * length * goal_rng.uniform() ** (1.0 / lay.dim) / max(np.linalg.norm(offset), 1e-12)
        controller = build("ours", cfg, sim, dyn, data, trained, progress=False)   # as the experiments fly it
        sim.reset()   # where it rests: the episode resets to the same state
        p0 = sim.state(noisy=False).p
        task = Task(start=p0, target=p0 + offset, seconds=float(agg.seconds), n_s=lay.n_s)
        controller.reset(task)
        lost = LossOfControl(task, cfg.flight)   # as the experiments' flights: a flipped drone's states are not flight
        sim.rng = np.random.default_rng(ss_noise)   # the flight's noise, from its own seed

        def act(t, state):
            if lost.check(state) is not None:
                raise _Ended("loss of control")
            u = np.asarray(controller.act(t, state), dtype=float)
            if not np.all(np.isfinite(u)):
                raise _Ended("controller failure")
            return np.clip(u, -drone.max_thrust, drone.max_thrust)
        try:
            ends[episode(sim, lay, act, rows, flight, dt, steps, float(cfg.data.region) ** 2)] += 1
        except LqrFailure:   # the controller's failure ends the flight's transitions there
            ends["controller failure"] += 1
        except _Ended as end:
            ends[str(end)] += 1
    arrays = {k: v[:rows.i] for k, v in rows.arrays().items()}
    names = sorted(ends)
    return {**arrays, "end_names": np.array(names), "end_counts": np.array([ends[n] for n in names])}
