"""Neural dynamics identification for a config: its training data (sdexp.model.dataset), the
d, g, h networks trained on them (sdexp.model.training) and their LearnedDynamics
(sdexp.model.dynamics), each from its cache where it is there. What every experiment that
tests or flies the learned model starts from."""
from __future__ import annotations

import dataclasses

from sdexp.errors import UserError
from sdexp.model.dataset import Dataset, load_dataset
from sdexp.model.dynamics import LearnedDynamics
from sdexp.model.specs import DECOMPOSED
from sdexp.model.training import TrainedNets, ensemble, member_seed, train_models


def identify(cfg, progress: bool = True, priors: dict | None = None) -> tuple[Dataset, TrainedNets, LearnedDynamics]:
    """(dataset, trained d/g/h, LearnedDynamics) for ``cfg`` (the typed config). With
    ``model.ensemble`` K > 1, each net is the mean of K trained from member seeds, each member
    cached as the nets of ensemble 1 at its seed."""
    _check_prior(cfg, priors)   # before the data are made
    data = load_dataset(cfg)
    return (data, *identify_on(cfg, data, progress, priors))


def _check_prior(cfg, priors) -> None:
    if cfg.model.prior != "none" and not priors:
        raise UserError(f"model.prior = {cfg.model.prior}: the nets' prior is the drone's rest shape as a rigid "
                        "body, which this entry point does not read; run it through an experiment (sdexp "
                        "experiment=...), or set model.prior=none")


def identify_on(cfg, data: Dataset, progress: bool = True, priors: dict | None = None
                ) -> tuple[TrainedNets, LearnedDynamics]:
    """(trained d/g/h, LearnedDynamics) of ``cfg``'s model trained on ``data`` (the config's own, or
    more: sdexp.eval.aggregation); the nets cached by the data's content. With ``model.prior:
    rigid`` the rigid body's response ``priors`` (train_models'), which the learning side cannot
    read from the drone itself: the experiments' runners give it (sdexp.eval.learning)."""
    _check_prior(cfg, priors)
    one = dataclasses.replace(cfg.model, ensemble=1)
    trained = ensemble([train_models(data, one, member_seed(cfg.seed, k), cfg.cache_dir,
                                     float(cfg.data.validation_fraction), DECOMPOSED, progress,
                                     priors if cfg.model.prior != "none" else None)
                        for k in range(int(cfg.model.ensemble))])
    dyn = LearnedDynamics.from_trained(trained, data, float(cfg.sim.control_dt), int(cfg.model.horizon),
                                       int(cfg.model.command_delay), str(cfg.model.frame))
    return trained, dyn
