"""Geometry generators, one per paper drone shape: ``SHAPES[name](...) -> Shape``.

Signature of every generator::

    make(size, thickness, num_rotors, num_sensors, params) -> Shape

``size`` are the bounding lengths (x, y[, z]) from the paper's table, ``thickness`` the plate
thickness (None: the y length), ``params`` shape-specific proportions (dict of floats).
"""
from sdexp.errors import UserError
from sdexp.sim.mesh.shapes.shapes2d import SHAPES as _SHAPES_2D
from sdexp.sim.mesh.shapes.shapes3d import SHAPES as _SHAPES_3D

SHAPES = {**_SHAPES_3D, **_SHAPES_2D}


# The paper's designs (supplement B's tables): rotors and peripheral IMUs each shape carries. The
# generators can place other counts (spread evenly, or by the sensor-tree rule), but a config runs
# the design: its rotor count exactly, and at most its IMUs (fewer measure fewer bends).
DESIGNS = {  # shape: (num_rotors, num_sensors)
    "donut": (4, 4), "star": (5, 4), "flower": (9, 8), "leaf": (4, 4), "octopus": (9, 8),
    "orange_peel": (5, 5), "engine": (6, 6), "bunny": (3, 3), "diamond": (4, 8), "elephant": (2, 3),
    "rainbow": (2, 4), "rod": (5, 8),
}


def check_design(cfg) -> None:
    """drone.num_rotors and drone.num_sensors against the shape's design (DESIGNS)."""
    if cfg.shape not in DESIGNS:
        return
    rotors, sensors = DESIGNS[cfg.shape]
    if int(cfg.num_rotors) != rotors:
        raise UserError(f"drone.num_rotors = {cfg.num_rotors} does not fit the {cfg.shape} design: "
                        f"allowed {rotors} (its rotor sites, supplement B)")
    if not 0 <= int(cfg.num_sensors) <= sensors:
        raise UserError(f"drone.num_sensors = {cfg.num_sensors} does not fit the {cfg.shape} design: "
                        f"allowed 0 to {sensors} peripheral IMUs (supplement B)")
