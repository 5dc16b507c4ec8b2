"""The learned model an experiment flies: the config's data and nets (sdexp.model.identification),
with what only the experiments' side can give them: the rest shape as a rigid body for the nets'
prior (``model.prior: rigid``; the learning side never reads the drone) and ours' own flights
added to the data in rounds (``data.aggregation``, sdexp.eval.aggregation)."""
from __future__ import annotations


def learned_model(cfg, drone, progress: bool = True):
    """(dataset, trained nets, LearnedDynamics) for ``cfg`` and its built ``drone``."""
    from sdexp.eval.aggregation import aggregate
    from sdexp.model.identification import identify
    from sdexp.sim.rigid.geometry import rigid_prior

    priors = rigid_prior(drone, float(cfg.sim.gravity)) if cfg.model.prior == "rigid" else None
    data, trained, dyn = identify(cfg, progress, priors)
    if int(cfg.data.aggregation.rounds) > 0:
        data, trained, dyn = aggregate(cfg, data, trained, dyn, progress, priors)
    return data, trained, dyn
