"""The simulator's own checks of a validated config (``sdexp.config.validate`` checks the
schema and the ranges; these need the simulator's parts): a built-in drone against its paper
design, a drone from a mesh file against its file (read before anything is meshed), and the
effects against the effect library. Run by the run's preflight (sdexp.eval.run) and the
Gymnasium environments' config, before a folder or a mesh is made."""
from __future__ import annotations

from omegaconf import DictConfig, ListConfig, OmegaConf

from sdexp.config import check_edge_length


def check_config(cfg) -> None:
    """Raise UserError naming the first key the simulator cannot take."""
    from sdexp.sim.mesh.shapes import check_design
    from sdexp.sim.physics.effects import check_config_effects, resolve_effect
    d = cfg.drone
    if d.mesh.file is None:
        check_design(d)
    else:
        from sdexp.sim.mesh.shapes.from_file import check_file_drone
        size, given = check_file_drone(d)
        if given is None:   # a volume mesh given as such is not meshed: its own count is checked
            check_edge_length(d, size)

    def plain(x):
        return OmegaConf.to_container(x, resolve=True) if isinstance(x, (DictConfig, ListConfig)) else x
    check_config_effects(plain(cfg.sim.effects))   # names, parameters and ranges, before the run starts
    for e in cfg.discrepancy.candidates:           # names and importable classes, before the logs are read
        resolve_effect(plain(e), "discrepancy.candidates")
