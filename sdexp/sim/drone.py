"""build_drone(cfg): shape -> mesh (cached) -> FEM model, rotor patches and IMU patches."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sdexp import conf
from sdexp.cache import cached_arrays, config_key, key_of
from sdexp.errors import UserError
from sdexp.config import ELEMENTS
from sdexp.sim.physics.fem import FemModel, build_fem
from sdexp.sim.physics.quadratic import boundary_subfaces, quadratic_mesh
from sdexp.sensing import SensorLayout
from sdexp.sim.sensors import ImuPatches, build_imu_patches
from sdexp.sim.mesh.shape import Shape
from sdexp.sim.mesh.surface import boundary_faces, patch_faces
from sdexp.sim.mesh.traction import disc_weights

MESH_FORMAT = 2      # 2: the key holds every drone.mesh field (sdexp.cache.config_key)
LAYERED_FORMAT = 2   # bump when shapes3d._Plate.layered_mesh changes what it makes
EXACT_OUTLINE_FORMAT = 1   # bump when shapes3d._graded_closed changes what it makes


@dataclass
class RotorPatches:
    """CSR lists: the surface faces whose area-weighted normal is the thrust direction, and
    the nodes the thrust loads with their shares (a uniform traction over the patch's disc)."""
    face_ptr: np.ndarray
    faces: np.ndarray
    vert_ptr: np.ndarray
    verts: np.ndarray
    weights: np.ndarray
    anchors: np.ndarray   # (m, dim) rest anchor points of the design
    normals: np.ndarray   # (m, dim) the design's unit thrust directions there (the mesh's patch
                          # normals approach them; sdexp.eval.convergence loads along these)
    radius: float = 0.0   # the faces' centroids are within this of the anchor (drone.rotor_radius)

    @property
    def count(self) -> int:
        return len(self.face_ptr) - 1


@dataclass
class Drone:
    name: str
    fem: FemModel
    boundary: np.ndarray      # (nf, dim) outward-oriented surface triangles / segments
    rotors: RotorPatches
    imus: ImuPatches
    layout: SensorLayout
    max_thrust: float
    damping: float            # mass-proportional damping of the vertex velocities (1/s)
    deformation_damping: float  # ... of their part relative to the rigid motion (1/s)

    @property
    def dim(self) -> int:
        return self.fem.dim

    @property
    def num_rotors(self) -> int:
        return self.rotors.count


def drone_names() -> list[str]:
    return conf.paper_drones()


def make_shape(cfg) -> Shape:
    if cfg.mesh.file is not None:   # a drone of one's own: the file replaces the shape generator
        from sdexp.sim.mesh.shapes.from_file import make_file_shape
        return make_file_shape(cfg)
    from sdexp.sim.mesh.shapes import SHAPES
    if cfg.shape not in SHAPES:
        raise UserError(f"drone.shape = {cfg.shape!r} is unknown: choose one of {sorted(SHAPES)}")
    from sdexp.sim.mesh.shapes import check_design
    check_design(cfg)   # rotor and IMU counts against the paper's design
    try:
        shape = SHAPES[cfg.shape](list(cfg.size), cfg.thickness, int(cfg.num_rotors),
                                  int(cfg.num_sensors), dict(cfg.params))
    except ValueError as err:
        raise UserError(f"drone {cfg.name}: {err}") from None
    if len(shape.rotors) != cfg.num_rotors:
        raise UserError(f"drone.num_rotors = {cfg.num_rotors} but the {cfg.shape} shape places "
                        f"{len(shape.rotors)} rotors")
    if len(shape.imus) != cfg.num_sensors:
        raise UserError(f"drone.num_sensors = {cfg.num_sensors} but the {cfg.shape} shape places "
                        f"{len(shape.imus)} peripheral IMUs")
    return shape


def mesh_shape(shape: Shape, mesh, cache_dir: str, name: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Mesh ``shape`` with the ``drone.mesh`` settings (a MeshConfig), through the cache; a mesh
    made (not read from the cache) is a logged phase, named by ``name`` (the drone's). A volume
    mesh the shape brings (a file of tets) is used as it is."""
    if shape.volume_mesh is not None:
        points, elems = shape.volume_mesh
        return points, elems.astype(np.int32)
    planes = list(mesh.mirror)
    layers = int(mesh.layers)
    payload = {"v": shape.vertices.round(12).tolist(), "f": shape.faces.tolist(),
               "h": shape.holes.round(12).tolist(), "mesh": config_key(mesh), "layered": LAYERED_FORMAT}
    if mesh.outline == "exact":   # keyed apart so that the drones' own meshes keep their keys
        payload["exact_outline"] = EXACT_OUTLINE_FORMAT
    if layers and shape.layered_mesh is None:
        raise UserError(f"drone.mesh.layers = {layers}: the {shape.dim}D shape is not a plate; set it to 0")
    if planes:
        from sdexp.sim.mesh.mirror import asymmetric_parts
        bad = asymmetric_parts(shape, planes)
        if bad:
            raise UserError(f"drone.mesh.mirror = {planes}: the design is not symmetric there, its "
                            f"{', '.join(bad)} do not mirror onto themselves")

    def make() -> dict[str, np.ndarray]:
        from sdexp.log import Phase
        how = "layered" if layers else "fTetWild" if shape.dim == 3 else "Triangle"
        with Phase(f"meshing {name or f'a {shape.dim}D shape'} ({how}, edge {mesh.edge_length:g} m)") as phase:
            made = _make()
            phase.close(f"{len(made['elems']):,} elements, {len(made['points']):,} nodes")
        return made

    def _make() -> dict[str, np.ndarray]:
        if layers:
            from sdexp.sim.mesh.mirror import AXES, reflect_all
            try:
                pts, el = reflect_all(*shape.layered_mesh(mesh.edge_length, layers, tuple(AXES[p] for p in planes),
                                                          mesh.outline == "exact"),
                                      planes)
            except ValueError as err:
                raise UserError(f"drone.mesh.mirror = {planes}: {err}") from None
        elif shape.dim == 3:
            from sdexp.sim.mesh.tetmesh import tet_mesh

            def tets(vertices, faces):
                return tet_mesh(vertices, faces, mesh.edge_length, mesh.stop_energy, mesh.coarsen, mesh.envelope)
            if planes:
                from sdexp.sim.mesh.mirror import AXES, symmetric_mesh
                try:
                    cell = shape.cell_surface(tuple(AXES[p] for p in planes))
                except ValueError as err:
                    raise UserError(f"drone.mesh.mirror = {planes}: {err}") from None
                pts, el = symmetric_mesh(cell, planes, tets)
            else:
                pts, el = tets(shape.vertices, shape.faces)
        else:
            from sdexp.sim.mesh.trimesh import tri_mesh
            pts, el = tri_mesh(shape.vertices, shape.faces, shape.holes, mesh.edge_length)
        return {"points": pts, "elems": el}

    arrays = cached_arrays(cache_dir, key_of(f"mesh{shape.dim}d", MESH_FORMAT, payload), make)
    return arrays["points"], arrays["elems"].astype(np.int32)


def _csr(lists: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    ptr = np.concatenate([[0], np.cumsum([len(x) for x in lists])]).astype(np.int64)
    flat = np.concatenate(lists) if lists else np.zeros(0, dtype=np.int64)
    return ptr, flat


def build_rotors(points, elems, boundary, anchors, normals, radius, name) -> RotorPatches:
    """Each rotor's patch: the boundary faces (of ``boundary``, the simulator's linear pieces)
    whose centroid lies within ``radius`` of its anchor, facing its normal, whose area-weighted
    normal is the thrust's direction in flight; and the nodes of ``elems`` the thrust loads, a
    uniform traction over the disc of ``radius`` (traction.disc_weights)."""
    face_lists, vert_lists, weight_lists = [], [], []
    for r, (a, n) in enumerate(zip(anchors, normals)):
        idx = patch_faces(points, boundary, a, n, radius)
        if len(idx) == 0:
            raise UserError(f"drone {name}: rotor {r} finds no surface facing {n.round(2).tolist()}")
        face_lists.append(boundary[idx])
        nodes, w = disc_weights(points, elems, np.asarray(a, float), np.asarray(n, float), radius)
        vert_lists.append(nodes)
        weight_lists.append(w)
    face_ptr = np.concatenate([[0], np.cumsum([len(f) for f in face_lists])]).astype(np.int64)
    faces = np.concatenate(face_lists).astype(np.int64)
    if faces.shape[1] == 2:  # keep a (k, 3) array for the numba kernel's single signature
        faces = np.c_[faces, faces[:, :1]]
    vert_ptr, verts = _csr(vert_lists)
    normals = np.asarray(normals, dtype=float)
    return RotorPatches(face_ptr, faces, vert_ptr, verts.astype(np.int64), np.concatenate(weight_lists),
                        np.asarray(anchors), normals / np.linalg.norm(normals, axis=1, keepdims=True),
                        float(radius))


def drone_length(drone_cfg, drone: Drone) -> float:
    """The drone's largest dimension (m): the design's bounding lengths (drone.size), or for a
    drone from a mesh file (no size given) its rest shape's bounding box."""
    size = list(drone_cfg.size)
    if size:
        return float(max(size))
    rest = drone.fem.rest
    return float((rest.max(axis=0) - rest.min(axis=0)).max())


def build_drone(cfg, cache_dir: str, element: str) -> Drone:
    """cfg is the ``drone`` config node (validated); ``element``: ``sim.element``."""
    shape = make_shape(cfg)
    points, elems = mesh_shape(shape, cfg.mesh, cache_dir, cfg.name)
    return assemble_drone(cfg, shape, points, elems, element)


def assemble_drone(cfg, shape: Shape, points: np.ndarray, elems: np.ndarray, element: str) -> Drone:
    """Bind rotors and IMUs of ``shape`` to the linear mesh (points, elems), with ``element``
    (linear | quadratic) elements on it; cfg supplies the material, mass, thrust limit and
    patch radii (a DroneConfig or anything with its fields)."""
    corner_faces = boundary_faces(elems)
    if element == "quadratic":
        points, elems = quadratic_mesh(points, elems)
        boundary = boundary_subfaces(corner_faces, elems)
    elif element == "linear":
        boundary = corner_faces
    else:
        raise UserError(f"sim.element = {element!r} is unknown: choose one of {list(ELEMENTS)}")
    try:
        fem = build_fem(points, elems, cfg.mass, cfg.youngs_modulus, cfg.poisson_ratio)
    except ValueError as err:
        raise UserError(f"drone {cfg.name}: its mesh (drone.mesh = edge_length {cfg.mesh.edge_length}) "
                        f"gives no usable FEM model: {err}") from None
    rotors = build_rotors(points, elems, boundary, shape.rotors, shape.rotor_normals, cfg.rotor_radius, cfg.name)
    imus, layout = build_imu_patches(points, boundary, shape, cfg.imu_radius, cfg.name)
    return Drone(cfg.name, fem, boundary, rotors, imus, layout, float(cfg.max_thrust),
                 float(cfg.damping), float(cfg.deformation_damping))
