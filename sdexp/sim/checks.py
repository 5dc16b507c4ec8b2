"""The simulator's own checks of a config (``sdexp.config.validate`` checks the schema and the
ranges; these need the simulator's parts): a built-in drone against its paper design, a drone
from a mesh file against its file (read before anything is meshed), and the effects against the
effect library. Run by the run's preflight (sdexp.eval.run) and the Gymnasium environments'
config, before a folder or a mesh is made; plain arguments (the preflight converts)."""
from __future__ import annotations

from sdexp.config import check_edge_length


def check_config(drone, effects: list, candidates: list) -> None:
    """Raise UserError naming the first key the simulator cannot take: ``drone`` the drone config
    (any object with its fields), ``effects`` sim.effects and ``candidates`` discrepancy.candidates
    as plain lists."""
    from sdexp.sim.mesh.shapes import check_design
    from sdexp.sim.physics.effects import check_config_effects, resolve_effect
    if drone.mesh.file is None:
        check_design(drone)
    else:
        from sdexp.sim.mesh.shapes.from_file import check_file_drone
        size, given = check_file_drone(drone)
        if given is None:   # a volume mesh given as such is not meshed: its own count is checked
            check_edge_length(drone, size)
    check_config_effects(effects)    # names, parameters and ranges, before the run starts
    for e in candidates:             # names and importable classes, before the logs are read
        resolve_effect(e, "discrepancy.candidates")
