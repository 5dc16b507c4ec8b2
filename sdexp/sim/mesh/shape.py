"""What a geometry generator hands to the mesher and the drone builder.

Every drone lies in the X-Z plane at rest with +Y up (gravity along -Y); 2D drones live in
the X-Y plane. Anchors are points near the upper (+Y) surface; the drone builder binds each
to the mesh vertices of the upper surface within a radius.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np


@dataclass
class Shape:
    dim: int
    # 3D: closed, outward-oriented triangle surface; 2D: boundary polygon(s) as segments.
    vertices: np.ndarray          # (n, dim) float
    faces: np.ndarray             # 3D: (m, 3) triangles; 2D: (m, 2) segments
    holes: np.ndarray             # 2D only: (k, 2) one point inside each hole; 3D: (0, 3)
    center: np.ndarray            # (dim,) root of the sensor tree (geometric centre)
    rotors: np.ndarray            # (num_rotors, dim) rotor anchors
    rotor_normals: np.ndarray     # (num_rotors, dim) unit thrust direction at rest (picks the side)
    imus: np.ndarray              # (num_sensors, dim) peripheral IMU anchors, the order of s
    imu_normals: np.ndarray       # (num_sensors, dim) unit surface normal at each IMU at rest
    frame_imus: np.ndarray        # (k, dim) IMU anchors whose averaged frame defines e (k=1: centre)
    frame_normals: np.ndarray     # (k, dim)
    # 3D plates: axes (0: x, 2: z) -> closed surface of the part on the positive side of the
    # mirror planes through the centre normal to them (drone.mesh.mirror, sdexp.sim.mesh.mirror)
    cell_surface: Optional[Callable[[tuple], tuple]] = None
    # 3D plates: (edge, layers, mirror axes, exact outline) -> (points, tets) extruded through the thickness
    layered_mesh: Optional[Callable[[float, int, tuple, bool], tuple]] = None
    # a volume mesh (points, elements) given as such (drone.mesh.file of tets): used as it is
    volume_mesh: Optional[tuple] = None
