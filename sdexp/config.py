"""Structured configs: the schema every YAML file in conf/ is merged onto.

A misspelled key in a YAML file or on the command line is an error because these dataclasses
are registered as the root schema (``base_config`` in conf/config.yaml's defaults list).
Physical ranges are checked by :func:`validate`, which names the key and the allowed range.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from sdexp.errors import UserError


@dataclass
class MeshConfig:
    edge_length: float = 0.2   # target element edge length (m); the resolution knob
    stop_energy: float = 10.0  # fTetWild quality target (3D only); lower = better tets, slower
    coarsen: bool = False      # fTetWild drops every vertex it can while keeping the quality


@dataclass
class DroneConfig:
    name: str = MISSING
    dim: int = 3                       # 3 (tets) or 2 (triangles, plane strain)
    shape: str = MISSING               # geometry generator in sdexp.sim.shapes
    size: List[float] = MISSING        # bounding lengths (x, y[, z]) in metres, y is "up"
    thickness: Optional[float] = None  # plate thickness when the shape is not a flat plate
    mass: float = 1.0                  # kg
    youngs_modulus: float = MISSING    # Pa
    poisson_ratio: float = 0.3         # the paper does not state it
    damping: float = 1.0               # mass-proportional damping coefficient (1/s)
    num_rotors: int = MISSING
    num_sensors: int = MISSING         # peripheral IMUs, i.e. the length of s
    max_thrust: float = 10.0           # N per rotor; commands are clipped to [-max, max]
    rotor_radius: float = 0.12         # radius of the vertex patch a rotor is bound to (m)
    imu_radius: float = 0.12           # radius of the vertex patch an IMU is bound to (m)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    params: Dict[str, float] = field(default_factory=dict)  # shape-specific proportions


@dataclass
class BoxConfig:
    min: List[float] = MISSING
    max: List[float] = MISSING


@dataclass
class SimConfig:
    control_dt: float = 0.01             # s; the control loop runs at 100 Hz
    substep: Optional[float] = None      # s; None = largest stable explicit step x safety
    stability_safety: float = 0.8        # fraction of the estimated stability limit 2/omega_max
    gravity: float = 9.81                # m/s^2 along -y
    ground: Optional[float] = None       # height of a ground plane, None = no ground
    obstacles: List[BoxConfig] = field(default_factory=list)  # static axis-aligned boxes
    friction: float = 0.5                # Coulomb coefficient on ground and boxes
    max_speed: float = 100.0             # m/s; faster vertices count as a blow-up
    max_stretch: float = 4.0             # body extent / rest extent beyond which it has blown up
    threads: int = 0                     # FEM kernel threads; 0 = auto (2 for big meshes)


@dataclass
class NoiseConfig:
    enabled: bool = True
    angle_std_deg: float = 0.573      # Gaussian on every angle reading (paper, supplement E)
    position_std: float = 0.01        # m, Gaussian on every position reading
    angle_rate_std_deg: float = 0.573  # deg/s on angle rates: our reading of the table
    velocity_std: float = 0.01        # m/s on velocities: our reading of the table
    rotor_std: float = 0.1            # N, Gaussian perturbation of every applied thrust
    delay: float = 0.03               # s between command and the rotors applying it


@dataclass
class DataConfig:
    """Training data (supplement F): random thrust holds from the undeformed drone at rest."""
    samples: int = 150_000          # transitions (one per 10 ms control step)
    hold_seconds: float = 1.0       # each rotor's thrust is redrawn from U[-Tmax, Tmax] this often
    episode_seconds: float = 30.0   # an episode also ends on a failure or leaving the region
    region: float = 30.0            # m from the start beyond which an episode restarts
    workers: int = 2                # simulation processes
    validation_fraction: float = 0.1  # held-out episodes


@dataclass
class ModelConfig:
    """The d, g, h networks (Eq. 4) and their training (supplement F)."""
    hidden: int = 128
    blocks: int = 4                 # residual blocks of linear layers with ReLU
    epochs: int = 50
    batch_size: int = 512
    lr: float = 1e-3
    lr_decay: float = 0.8           # multiplied in every lr_step epochs
    lr_step: int = 20
    loss: str = "l1"                # l1 | l2
    keep_best: bool = True          # return the epoch of lowest validation loss (false: the last, as the paper)
    threads: int = 2                # torch threads: >= 2 trains d, g, h side by side, one thread each


@dataclass
class ExperimentConfig:
    name: str = MISSING
    params: Dict[str, Any] = field(default_factory=dict)


@dataclass
class Config:
    seed: int = 0
    cache_dir: str = "${oc.env:SDEXP_CACHE,${oc.env:HOME}/.cache/sdexp}"
    drone: DroneConfig = field(default_factory=DroneConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)


def register() -> None:
    ConfigStore.instance().store(name="base_config", node=Config)


def _check(ok: bool, key: str, value: Any, allowed: str) -> None:
    if not ok:
        raise UserError(f"{key} = {value!r} is not physical: allowed {allowed}")


def validate(cfg: DictConfig | Config) -> None:
    """Raise UserError naming the first key whose value is outside its physical range."""
    d, s, n = cfg.drone, cfg.sim, cfg.noise
    _check(d.dim in (2, 3), "drone.dim", d.dim, "2 or 3")
    _check(len(d.size) == d.dim, "drone.size", list(d.size), f"{d.dim} positive lengths")
    _check(all(x > 0 for x in d.size), "drone.size", list(d.size), "all lengths > 0")
    _check(d.mass > 0, "drone.mass", d.mass, "> 0 kg")
    _check(d.youngs_modulus > 0, "drone.youngs_modulus", d.youngs_modulus, "> 0 Pa")
    _check(0 < d.poisson_ratio < 0.5, "drone.poisson_ratio", d.poisson_ratio, "in (0, 0.5)")
    _check(d.damping >= 0, "drone.damping", d.damping, ">= 0 1/s")
    _check(d.max_thrust > 0, "drone.max_thrust", d.max_thrust, "> 0 N")
    _check(d.num_rotors >= 1, "drone.num_rotors", d.num_rotors, ">= 1")
    _check(d.num_sensors >= 0, "drone.num_sensors", d.num_sensors, ">= 0")
    _check(d.thickness is None or d.thickness > 0, "drone.thickness", d.thickness, "> 0 m")
    _check(d.mesh.edge_length > 0, "drone.mesh.edge_length", d.mesh.edge_length, "> 0 m")
    _check(s.control_dt > 0, "sim.control_dt", s.control_dt, "> 0 s")
    _check(s.substep is None or 0 < s.substep <= s.control_dt, "sim.substep", s.substep,
           "null or in (0, sim.control_dt]")
    _check(0 < s.stability_safety <= 1, "sim.stability_safety", s.stability_safety, "in (0, 1]")
    _check(s.threads >= 0, "sim.threads", s.threads, ">= 0 (0 = auto)")
    _check(s.friction >= 0, "sim.friction", s.friction, ">= 0")
    for i, b in enumerate(s.obstacles):
        _check(len(b.min) == len(b.max) == d.dim and all(a < c for a, c in zip(b.min, b.max)),
               f"sim.obstacles[{i}]", OmegaConf.to_container(b) if isinstance(b, DictConfig) else b,
               f"min < max, {d.dim} coordinates each")
    a, m = cfg.data, cfg.model
    _check(a.samples > 0, "data.samples", a.samples, "> 0")
    _check(a.hold_seconds > 0, "data.hold_seconds", a.hold_seconds, "> 0 s")
    _check(a.episode_seconds >= a.hold_seconds, "data.episode_seconds", a.episode_seconds, ">= data.hold_seconds")
    _check(a.region > 0, "data.region", a.region, "> 0 m")
    _check(a.workers >= 1, "data.workers", a.workers, ">= 1")
    _check(0 < a.validation_fraction < 1, "data.validation_fraction", a.validation_fraction, "in (0, 1)")
    _check(m.hidden >= 1 and m.blocks >= 1, "model.hidden/blocks", (m.hidden, m.blocks), ">= 1")
    _check(m.epochs >= 1, "model.epochs", m.epochs, ">= 1")
    _check(m.batch_size >= 1, "model.batch_size", m.batch_size, ">= 1")
    _check(m.lr > 0 and 0 < m.lr_decay <= 1 and m.lr_step >= 1, "model.lr/lr_decay/lr_step",
           (m.lr, m.lr_decay, m.lr_step), "lr > 0, lr_decay in (0, 1], lr_step >= 1")
    _check(m.loss in ("l1", "l2"), "model.loss", m.loss, "l1 or l2")
    for key in ("angle_std_deg", "position_std", "angle_rate_std_deg", "velocity_std",
                "rotor_std", "delay"):
        _check(getattr(n, key) >= 0, f"noise.{key}", getattr(n, key), ">= 0")
