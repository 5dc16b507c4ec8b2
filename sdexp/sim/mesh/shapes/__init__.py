"""Geometry generators, one per paper drone shape: ``SHAPES[name](...) -> Shape``.

Signature of every generator::

    make(size, thickness, num_rotors, num_sensors, params) -> Shape

``size`` are the bounding lengths (x, y[, z]) from the paper's table, ``thickness`` the plate
thickness (None: the y length), ``params`` shape-specific proportions (dict of floats).
"""
from sdexp.sim.mesh.shapes.shapes2d import SHAPES as _SHAPES_2D
from sdexp.sim.mesh.shapes.shapes3d import SHAPES as _SHAPES_3D

SHAPES = {**_SHAPES_3D, **_SHAPES_2D}
