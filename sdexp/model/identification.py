"""Neural dynamics identification for a config: its training data (sdexp.model.dataset), the
d, g, h networks trained on them (sdexp.model.training) and their LearnedDynamics
(sdexp.model.dynamics), each from its cache where it is there. What every experiment that
tests or flies the learned model starts from."""
from __future__ import annotations

from sdexp.model.dataset import Dataset, load_dataset
from sdexp.model.dynamics import LearnedDynamics
from sdexp.model.specs import DECOMPOSED
from sdexp.model.training import TrainedNets, train_models


def identify(cfg, progress: bool = True) -> tuple[Dataset, TrainedNets, LearnedDynamics]:
    """(dataset, trained d/g/h, LearnedDynamics) for ``cfg`` (the typed config)."""
    data = load_dataset(cfg)
    trained = train_models(data, cfg.model, int(cfg.seed), cfg.cache_dir, float(cfg.data.validation_fraction),
                           DECOMPOSED, progress)
    dyn = LearnedDynamics.from_trained(trained, data, float(cfg.sim.control_dt), int(cfg.model.horizon),
                                       int(cfg.model.command_delay))
    return data, trained, dyn
