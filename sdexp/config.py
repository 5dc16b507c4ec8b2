"""Structured configs: the schema every YAML file in conf/ is merged onto.

A misspelled key in a YAML file or on the command line is an error because these dataclasses
are registered as the root schema (``base_config`` in conf/config.yaml's defaults list).
A field declares its physical range in its metadata (sdexp.ranges); :func:`validate` reads them
with the one checker the experiments' params and the effects use too, then checks what depends on
two keys at once, and names the key and the allowed range.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import typing
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sdexp.cache import KEY_UNLESS_DEFAULT
from sdexp.errors import UserError, did_you_mean, one_line
from sdexp.ranges import at_least, between, check_fields, choices, nonnegative, param, positive, ranged


ELEMENTS = ("linear", "quadratic")   # sim.element: the FEM element order (sdexp.sim.physics.fem)
# sim.mass_scaling's ceiling: x1.35 on the flower's step already costs +2.6% mass and 3.5% in its
# frequencies, x1.5 8% and 9% (issue 25): a tenth of the mass is far past any useful budget
MAX_MASS_SCALING = 0.1
MODELS = ("full", "reduced")   # sim.model: the full FEM (the reference) or the reduced-order model (sdexp.sim.reduced)
PRECISIONS = ("float64", "float32")  # sim.precision: the elastic forces' arithmetic (sdexp.sim.physics.fem.PRECISIONS)

# A field that says how a result is computed (threads, worker processes), not what: it is left
# out of the cache keys of the artefacts it helps make (sdexp.cache.config_key).
NOT_KEY = {"key": False}
# A field added after caches were built: keyed only away from its default (sdexp.cache.config_key).
UNLESS_DEFAULT = {"key": KEY_UNLESS_DEFAULT}


def mesh_path(path: str) -> Path | None:
    """Where ``drone.mesh.file = path`` is: a relative path in the working directory, else in
    sdexp's drone configs (the shipped example's mesh, so ``drone=tripod`` runs from any folder);
    None when in neither."""
    for p in mesh_path_candidates(path):
        if p.is_file():
            return p
    return None


def mesh_path_candidates(path: str) -> list[Path]:
    given = Path(path).expanduser()
    return [given] if given.is_absolute() else [Path.cwd() / given, Path(str(files("sdexp.conf"))) / "drone" / given]


@dataclass
class MeshConfig:
    edge_length: float = 0.2   # target element edge length (m); the resolution knob
    stop_energy: float = param(10.0, positive())  # fTetWild quality target (3D only); lower = better tets, slower
    coarsen: bool = False      # fTetWild drops every vertex it can while keeping the quality
    mirror: List[str] = field(default_factory=list)  # 3D: mesh one cell, reflect across x = 0 / z = 0
                                                     # (sdexp.sim.mesh.mirror); [] = mesh the whole body
    layers: int = 0            # 3D: 0 = fTetWild tetrahedralises the closed surface; n >= 1 = the outline
                               # triangulated and extruded through the thickness in n layers (no slivers)
    # layered 3D plates: "resampled" = the outline resampled evenly edge_length apart (the drones'
    # meshes); "exact" = the design's outline with its corners, graded toward the re-entrant ones
    # (the converged references of sdexp.eval.convergence: an even resampling cuts narrow notches)
    outline: str = field(default="resampled", metadata=UNLESS_DEFAULT)
    # 3D, fTetWild: how far its surface may stray from the given one, relative to the body's bounding
    # box diagonal; null: fTetWild's own 1e-3 (the drones' meshes). The converged references of a
    # drone of one's own mesh its file with a tighter one (sdexp.eval.convergence)
    envelope: Optional[float] = param(None, between(0, 0.01, "(]", "(relative to the bounding box diagonal) or null",
                                                    **UNLESS_DEFAULT))
    # A drone of one's own (sdexp.sim.mesh.meshfile): a closed surface or a tet mesh (3D), a closed
    # outline or a triangle mesh (2D), in any format meshio reads; null = the shape generator. Its
    # name is not part of the cache keys: its content is (digest), so an edited file is remeshed.
    file: Optional[str] = field(default=None, metadata=NOT_KEY)
    # scale and digest were added after caches were built: keyed only away from their defaults
    scale: float = field(default=1.0, metadata=UNLESS_DEFAULT)   # the file's unit in metres (0.001: millimetres)
    digest: Optional[str] = field(default=None, metadata=UNLESS_DEFAULT)  # sha256 of the file's bytes, filled in when the config is read; not an input

    def __post_init__(self) -> None:
        # OmegaConf.to_object constructs this: every typed config of a file drone carries its digest
        path = mesh_path(self.file) if self.file is not None else None
        self.digest = None if path is None else hashlib.sha256(path.read_bytes()).hexdigest()[:16]


@dataclass
class DroneConfig:
    name: str = MISSING
    dim: int = param(3, choices((2, 3)))   # 3 (tets) or 2 (triangles, plane strain)
    shape: str = MISSING               # geometry generator in sdexp.sim.mesh.shapes
    size: List[float] = MISSING        # bounding lengths (x, y[, z]) in metres, y is "up"
    thickness: Optional[float] = param(None, positive("m"))  # plate thickness when the shape is not a flat plate
    mass: float = param(1.0, positive("kg"))
    youngs_modulus: float = param(MISSING, positive("Pa"))
    poisson_ratio: float = param(0.3, between(0, 0.5, "()"))   # the paper does not state it
    damping: float = param(1.0, nonnegative("1/s"))   # mass-proportional damping of the vertex velocities (1/s)
    deformation_damping: float = param(20.0, nonnegative("1/s"))   # mass-proportional damping of the deformation velocity (1/s)
    num_rotors: int = MISSING
    num_sensors: int = param(MISSING, nonnegative())   # peripheral IMUs, i.e. the length of s
    max_thrust: float = param(10.0, positive("N"))   # N per rotor; commands are clipped to [-max, max]
    rotor_radius: float = param(0.12, positive("m"))   # radius of the vertex patch a rotor is bound to (m)
    imu_radius: float = param(0.12, positive("m"))   # radius of the vertex patch an IMU is bound to (m)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    params: Dict[str, float] = field(default_factory=dict)  # shape-specific proportions
    # drone.mesh.file only (sdexp.sim.mesh.shapes.from_file): positions in metres (after mesh.scale)
    rotors: List[Any] = field(default_factory=list, metadata=UNLESS_DEFAULT)         # snapped onto the nearest surface facing ...
    rotor_normals: List[Any] = field(default_factory=list, metadata=UNLESS_DEFAULT)  # ... these thrust directions ([]: +Y)
    imus: List[Any] = field(default_factory=list, metadata=UNLESS_DEFAULT)           # peripheral IMUs, the order of s ([]: the rule)


@dataclass
class BoxConfig:
    min: List[float] = MISSING
    max: List[float] = MISSING


@dataclass
class ReducedConfig:
    """sim.reduced: the reduced-order model's build (sdexp.sim.reduced; docs/reduced_model.md)."""
    basis: int = param(64, between(4, 400, unit="deformation basis vectors"))
    linear_modes: int = param(12, between(0, 100, unit="free-free linear modes kept whole in the basis"))
    rotor_statics: bool = True   # each rotor's quasi-static response in the basis
    modal_derivatives: int = param(4, between(0, 30, unit="linear modes whose modal derivatives join the basis"))
    cubature: int = param(200, between(4, 5000, unit="elements at most"))
    tolerance: float = param(0.01, between(0, 1, "()", "relative error of the cubature's force fit to stop at"))
    snapshot_seconds: float = param(40.0, between(1, 3600, unit="s of full-model flight for the basis and cubature"))
    range_margin: float = param(1.5, between(1, 100, unit="x the snapshots' range of each modal coordinate"))
    # the rest stiffness among the linear modes made exact (a linear term within their span, set at
    # load: the low frequencies); false: the cubature's alone
    exact_modes: bool = True


@dataclass
class SimConfig:
    control_dt: float = param(0.01, positive("s"))   # s; the control loop runs at 100 Hz
    substep: Optional[float] = None      # s; None = largest stable explicit step x safety
    stability_safety: float = param(0.8, between(0, 1, "(]"))   # fraction of the estimated stability limit 2/omega_max
    gravity: float = param(9.81, nonnegative("m/s^2 (it points along -y)"))
    ground: Optional[float] = None       # height of a ground plane, None = no ground
    obstacles: List[BoxConfig] = field(default_factory=list)  # static axis-aligned boxes
    friction: float = param(0.5, nonnegative())   # Coulomb coefficient on ground and boxes
    max_speed: float = param(100.0, positive("m/s"))   # m/s; faster vertices count as a blow-up
    max_stretch: float = param(4.0, ranged(lambda v: v > 1, "> 1 (x the rest extent)"))   # body extent / rest extent beyond which it has blown up
    threads: int = param(0, nonnegative("(0 = auto)", **NOT_KEY))   # FEM kernel threads; 0 = auto (2 for big meshes)
    element: str = param("quadratic", choices(ELEMENTS))   # quadratic (10-node tets / 6-node triangles) | linear (4 / 3 nodes: locks)
    # elastic forces in float64 | float32 (positions and velocities stay float64); keyed only when not float64
    precision: str = param("float64", choices(PRECISIONS, **UNLESS_DEFAULT))
    # targeted inertial mass scaling: at most this fraction of the drone's mass added as inertia on
    # the nodes of the modes that limit the stable step (gravity on the physical mass); 0 = off
    mass_scaling: float = param(0.0, between(0, MAX_MASS_SCALING, unit="(added inertia as a fraction of the drone's mass; 0 = off)", **UNLESS_DEFAULT))
    effects: List[Any] = field(default_factory=list)  # physical effects (sdexp.sim.physics.effects), each {name|_target_, params}
    # full: the FEM on every node (the reference) | reduced: the reduced-order model built from it
    model: str = param("full", choices(MODELS, **UNLESS_DEFAULT))
    # the reduced model's build (read with sim.model = reduced); keyed only away from its defaults
    reduced: ReducedConfig = field(default_factory=ReducedConfig, metadata=UNLESS_DEFAULT)


@dataclass
class NoiseConfig:
    enabled: bool = True
    angle_std_deg: float = param(0.573, nonnegative())   # Gaussian on every angle reading (paper, supplement E)
    position_std: float = param(0.01, nonnegative())   # m, Gaussian on every position reading
    angle_rate_std_deg: float = param(0.573, nonnegative())   # deg/s on angle rates: our reading of the table
    velocity_std: float = param(0.01, nonnegative())   # m/s on velocities: our reading of the table
    rotor_std: float = param(0.1, nonnegative())   # N, Gaussian perturbation of every applied thrust
    delay: float = param(0.03, nonnegative())   # s between command and the rotors applying it


@dataclass
class AggregationConfig:
    """data.aggregation: on-policy data aggregation (sdexp.eval.aggregation). After the random
    thrust holds, ``rounds`` times: ours flies ``flights`` flights of ``seconds`` to goals drawn
    within ``reach`` body lengths of its release, their transitions (read from the IMUs as the
    data's) join the data, the nets are trained again. 0 rounds: the paper's data alone."""
    rounds: int = param(0, between(0, 10, unit="rounds"))
    flights: int = param(8, between(1, 1000, unit="flights a round"))
    seconds: float = param(5.0, between(0.1, 600, unit="s a flight"))
    reach: float = param(0.5, between(0, 10, unit="body lengths"))


@dataclass
class DataConfig:
    """Training data (supplement F): random thrust holds from the undeformed drone at rest."""
    samples: int = param(150_000, positive())   # transitions (one per 10 ms control step)
    hold_seconds: float = param(1.0, positive("s"))   # each rotor's thrust is redrawn from U[-Tmax, Tmax] this often
    thrust_range: List[float] = field(default_factory=lambda: [-1.0, 1.0])  # U[lo, hi] x Tmax (paper: [-1, 1])
    around_hover: bool = False      # true: each hold draws hover thrust + U[lo, hi] x Tmax (paper: false)
    hover: str = param("rigid", choices(("rigid", "shape")))   # that hover thrust: rigid (the rest shape's, weight spread evenly) |
                                    # shape (plus the no-lift pattern that keeps the body flattest, sim.statics)
    # deg: each rotor's draw narrowed to the thrust that bends the body at most this much on its own
    # (sdexp.model.generate.thrust_draw); null: every rotor draws the whole range (paper)
    bend_budget_deg: Optional[float] = param(None, between(0, 180, "(]", "deg, or null (no limit)", **UNLESS_DEFAULT))
    deform_range: float = param(0.0, between(0, 1, unit="x max_thrust"))   # x Tmax: largest rotor offset of a held thrust pattern with no net
                                    # lift or tilting torque on the rest shape (it only deforms); 0: none (paper)
    deform_hold_seconds: float = param(1.0, positive("s"))   # such a pattern is redrawn this often
    episode_seconds: float = 30.0   # an episode also ends on a failure or leaving the region
    region: float = param(30.0, positive("m"))   # m from the start beyond which an episode restarts
    workers: int = param(2, at_least(1, **NOT_KEY))   # simulation processes
    # the simulator the data are made on: null = sim.model (the flights' own) | full | reduced (the
    # reduced-order model, sim.reduced; the flights stay on sim.model). Keyed through the data's sim
    # config, which carries the model the data were made on (sdexp.model.dataset.dataset_spec)
    sim_model: Optional[str] = param(None, choices((None,) + MODELS, **NOT_KEY))
    validation_fraction: float = param(0.1, between(0, 1, "()"))   # held-out episodes
    # ours' own flights added to the data in rounds (off by default, the paper's data alone); the
    # random holds are the same with or without (sdexp.model.dataset.dataset_spec leaves it out)
    aggregation: AggregationConfig = field(default_factory=AggregationConfig, metadata=UNLESS_DEFAULT)


@dataclass
class ModelConfig:
    """The d, g, h networks (Eq. 4) and their training (supplement F)."""
    hidden: int = param(128, at_least(1))
    blocks: int = param(4, at_least(1))   # residual blocks of linear layers with ReLU
    epochs: int = param(50, at_least(1))
    batch_size: int = param(512, at_least(1))
    lr: float = param(1e-3, positive())
    lr_decay: float = param(0.8, between(0, 1, "(]"))   # multiplied in every lr_step epochs
    lr_step: int = param(20, at_least(1))
    loss: str = param("l1", choices(("l1", "l2")))
    keep_best: bool = True          # return the epoch of lowest validation loss (false: the last, as the paper)
    linear: List[str] = param([], choices(("d", "g", "h", "raw")))  # nets (d, g, h, raw) that are linear maps, no hidden layers
    horizon: int = param(1, at_least(1, "frame"))   # predict the velocity this many frames ahead (paper: 1); alpha = horizon x dt
    # control steps from a command to the thrust it sets (the rotors' lag: 3 under the paper's
    # 30 ms at 10 ms steps). The nets learn a state's change from the command acting on it, not
    # the one sent at the same step (with 0.1 s holds and a 3-step lag, the sent one halves the
    # learned torque map: docs/learned_dynamics.md), and ours predicts the state over the lag with
    # the commands already sent (control/relinearizing.py). 0: the paper's model
    command_delay: int = param(0, between(0, 100, unit="control steps", **UNLESS_DEFAULT))
    # d, g and h each the mean of this many nets, trained alike from different seeds (member 0 from
    # the run's seed: the nets of ensemble 1; sdexp.model.identification). One net's errors that
    # depend on its initialisation and its held-out split average out; 1: one net each (the paper)
    ensemble: int = param(1, between(1, 32, unit="nets per network", **UNLESS_DEFAULT))
    # world: the nets read the yaw and world-frame velocities (the paper); heading: they read the
    # tilt alone and h works in the heading frame, so no net can learn a dependence on which way
    # the drone faces, which its body does not have (sdexp.model.heading; 2D drones: no change)
    frame: str = param("world", choices(("world", "heading"), **UNLESS_DEFAULT))
    # none: the nets learn the whole velocity change (the paper) | rigid: g and h add it to the
    # change the rest shape's rigid body would make at level (thrust over mass and the torques
    # over inertia, weight) and learn the rest (sdexp.model.training.prior_maps; the experiments
    # read the rest shape, sdexp.sim.rigid.geometry.rigid_prior)
    prior: str = param("none", choices(("none", "rigid"), **UNLESS_DEFAULT))
    threads: int = field(default=2, metadata=NOT_KEY)   # torch threads: >= 2 trains d, g, h side by side, one thread each


@dataclass
class NeuralControllerConfig:
    """The neural-controller baseline (sdexp.control.neural), trained through d, g, h."""
    hidden: int = 64
    layers: int = 2
    iterations: int = param(300, at_least(1))
    batch: int = param(64, at_least(1))
    horizon: int = param(150, at_least(1))   # control steps back-propagated through
    lr: float = 1e-3
    goal_radius: float = param(6.0, positive("m"))   # m; training goals are drawn in a ball this large
    w_att: float = 1.0              # loss weights: attitude, bend, velocity, thrust
    w_bend: float = 0.1
    w_vel: float = 0.05
    w_u: float = 0.01


@dataclass
class ControlConfig:
    """Algorithm 1 and the LQR baselines (supplement G's table: Q gains 100-200 for s and p,
    50-200 for e, R = 2, kp = 0.03, kd = 0.0001, n = 10)."""
    q_s: float = param(100.0, positive())
    q_e: float = param(100.0, positive())
    q_p: float = param(100.0, positive())
    velocity_scale: float = param(1.0, nonnegative())   # Q on a rate = this x Q on its angle/position
    q_p_axes: Optional[List[float]] = None   # Q on position (and velocity) per axis = q_p x these (x, y[, z]);
                                             # null: q_p on every axis (the paper)
    q_e_axes: Optional[List[float]] = None   # Q on the Euler angles (and rates) = q_e x these (3D: e_x, e_y = yaw
                                             # about the up axis, e_z; 2D: one); null: q_e on each (the paper)
    r: float = param(2.0, positive())
    kp: float = param(0.03, between(0, 1))
    kd: float = param(0.0001, nonnegative())
    waypoint_max: Optional[float] = param(None, positive("or null"))   # ours: m, the waypoint's position offset at most this long
                                           # (a far goal approached steadily; null: kp alone, the paper)
    approach_speed: Optional[float] = param(None, positive("m/s or null"))   # ours, with waypoint_max: a goal
                                           # further than 2 waypoint_max is approached at this speed (the
                                           # waypoint's velocity points at it; ramps from 0 at waypoint_max).
                                           # null: the waypoint's velocity is the goal's (control/relinearizing.py)
    n: int = param(10, at_least(1, "control steps"))   # relinearise every n control steps (100/n Hz)
    relinearize: bool = True        # false: linearise once at a given operating point
    feedforward: bool = False       # ours: thrust that holds the goal's bends (not in the paper; relinearizing.py)
    riccati: str = param("continuous", choices(("continuous", "discrete")))   # continuous (the paper) | discrete (gain of the 100 Hz sampled loop)
    # ours regulates a bend channel only where its spread in the training data is at least this many
    # times the IMU angle noise (noise.angle_std_deg; noise off: every bend); below, the bend is
    # sensor noise and its learned dynamics a fit to noise (the stiff drones: spread 1.4-1.6x the
    # noise; every soft drone 11x or more). 0: every bend (the paper). control/lqr.py regulated_states
    bend_snr: float = param(3.0, nonnegative("(0: every bend)"))
    # ours: Q's weight on the differences of bends the task asks to move together (the same
    # non-zero target: the star's folding wings), q_s_alike x (s_a - s_b)^2 per pair; 0: the
    # paper's diagonal Q. control/lqr.py alike_weights
    q_s_alike: float = param(0.0, nonnegative("(0: the paper's diagonal Q)"))
    # ours: R's weight on thrust differences among the rotors that drive those bends (each bend's
    # rotor read from the learned model's B), r_alike x r x (u_a - u_b)^2 per pair; their common
    # thrust costs r as before; 0: the paper's diagonal R. control/lqr.py alike_thrust_weights
    r_alike: float = param(0.0, nonnegative("(0: the paper's diagonal R)"))
    # ours: each relinearisation moves the operating thrust this fraction of the way toward an even
    # share of its total, within the thrust directions the learned rigid motion does not feel; 0:
    # Algorithm 1 as written (the operating thrust is the last command). control/relinearizing.py
    share_pull: float = param(0.0, between(0, 1, unit="(0: Algorithm 1 as written)"))
    # ours: the share of the feedback's last correction the operating thrust keeps at each
    # relinearisation (with feedforward: the share the integral part keeps); 1: Algorithm 1 as
    # written, whose integral then acts within one period n. control/relinearizing.py
    integral: float = param(1.0, between(0, 1, "(]", "(1: Algorithm 1 as written)"))
    # s: every controller reads the decomposed state through a first-order low-pass of this time
    # constant, so that the rate feedback stops pumping a soft elastic mode the IMUs sit on (the
    # rainbow's 5 Hz mode, control/lowpass.py); 0: the state as read (the paper)
    lowpass: float = param(0.0, between(0, 1, unit="s (0: the state as read)"))
    # ours: the phase (deg) the feedback's fastest rate may lose over the command delay
    # (model.command_delay control steps): R is raised until max |eig(B K)| x delay <= this
    # (control/relinearizing.py max_rate); null: R as given (the paper)
    delay_phase_deg: Optional[float] = param(None, between(0, 180, "(]", "deg or null"))
    neural: NeuralControllerConfig = field(default_factory=NeuralControllerConfig)


@dataclass
class RecordConfig:
    """Flights of the simulator through manoeuvres (sdexp.discrepancy.record)."""
    flights: int = param(8, at_least(1))
    seconds: float = param(6.0, positive("s"))   # per flight, plus 1 s of settling
    manoeuvres: List[str] = field(default_factory=lambda: [
        "hover", "steps", "random_holds", "ground_pass", "differential", "high_speed"])
    height: float = 2.5                # m, start height of the lowest vertex above the ground
    ground: float = 0.0                # m, where the ground-pass manoeuvre skims to
    amplitude: float = param(0.3, nonnegative())   # excitation thrust as a fraction of the hover thrust


@dataclass
class DiscrepancyConfig:
    """The sim-vs-measured workflow (sdexp.discrepancy.workflow)."""
    measured: Optional[str] = None     # folder of measured logs (README: log format)
    out: Optional[str] = None          # where the fitted effect override is written; null = the run folder
    horizon: float = param(0.2, positive("s"))   # s predicted from each re-initialised measured state
    stride: float = param(0.5, positive("s"))   # s between window starts
    history: float = param(0.3, nonnegative("s"))   # s of commands replayed through the actuation chain first, at
                                       # least: a slow candidate asks for more (its FitSpec.memory)
    start_average: int = param(8, at_least(1, "rows"))   # rows the start state's p, e, s are averaged over (causal, rate-carried)
    holdout: float = param(0.5, between(0, 1, "()"))   # fraction of flights held out (at least one): tests need many windows
    fit_windows: int = 30              # training windows the fits use (evenly thinned): the cost driver
    candidates: List[Any] = field(default_factory=list)  # library names and {_target_: ...} entries;
                                                          # [] = the whole effect library
    alpha: float = param(0.05, between(0, 1, "()"))   # family-wise error rate of the candidate tests (Bonferroni)
    min_gain: float = param(0.02, nonnegative())   # smallest held-out relative improvement that names an effect
    screen: int = param(3, at_least(1))   # candidates refined and tested on held-out flights
    max_effects: int = param(2, at_least(1))   # effects added one after another while the residual remains
    # nominal simulated flights that calibrate the noise floor; null: as many as the unexplained
    # test needs on this drone (workflow.floor_flight_count: 8 or more, by its channel count)
    floor_flights: Optional[int] = param(None, at_least(1, "or null (as many as the unexplained test needs)"))
    unexplained_ratio: float = param(1.2, at_least(1, "(a multiple of the noise floor)"))   # a channel's residual / noise floor above which, if significant over
                                       # held-out flights and replicated on training flights, it is unexplained
    second_effect_ratio: float = param(1.5, at_least(1, "(a multiple of the noise floor)"))   # held-out loss / the floor's above which another effect is sought
    explained_enough: float = param(0.9, between(0, 1, "(]"))   # share of the gap below which named effects with channels left
                                       # above the floor are answered "partly" (the rest unexplained); correctly named
                                       # library effects that leave such channels close 0.96-1.0 (both benches)
    push: bool = True                  # the per-window push diagnostic (push.csv/png): 8 rollouts more
    record: RecordConfig = field(default_factory=RecordConfig)


@dataclass
class FlightConfig:
    """When a controlled flight (sdexp.control.rollout.fly) is lost: the same limits for every
    controller and task. Past either, the episode ends as ``loss_of_control`` with its reason and
    time, next to the simulator's blow-ups and the controller's failures (README "Metrics")."""
    max_tilt_deg: Optional[float] = param(90.0, between(0, 180, "(]", "deg or null"))  # angle between the body's up axis (the frame IMU's Y) and
                                          # world +Y; past 90 deg the rotors push the body down: the
                                          # paper's "illegal configuration". null: no tilt limit
    arena_margin: Optional[float] = param(10.0, positive("m or null"))  # m: the measured position may stray this far from the box
                                          # spanned by the task's start and its goal positions over the
                                          # task (p_goal(0), p_goal(seconds)); 10 m is over 3x the
                                          # SOTA task's 3 m legs, so only a flight gone astray leaves.
                                          # null: no arena


@dataclass
class ExperimentConfig:
    _target_: str = MISSING   # the runner, run(run: sdexp.eval.run.Run) -> metrics
    name: str = MISSING
    params: Any = None        # the experiment's own dataclass (sdexp.experiment_params), placed by its YAML


@dataclass
class Config:
    seed: int = 0
    cache_dir: str = "${oc.env:SDEXP_CACHE,${oc.env:HOME}/.cache/sdexp}"
    # CPU cores this run may use, its threads and worker processes together (sdexp.parallel.job_cores
    # caps sim.threads, data.workers, model.threads and torch/BLAS/numba threads by it); null = auto:
    # the cores this process may use (a Slurm job: its allocation) divided by the jobs that run beside
    # it on this machine (hydra/launcher=joblib: its n_jobs; submitit_local: the sweep's jobs)
    cores: Optional[int] = param(None, at_least(1, "or null (auto)"))
    # the multirun folder that ``sdexp experiment=report`` aggregates (experiment.params.sweep_dir)
    sweep_dir: Optional[str] = None
    drone: DroneConfig = field(default_factory=DroneConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    discrepancy: DiscrepancyConfig = field(default_factory=DiscrepancyConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)


def register() -> None:
    ConfigStore.instance().store(name="base_config", node=Config)
    # ${sdexp.pid:} in conf/config.yaml's run and sweep folders: two runs started in the same
    # second get different folders (sdexp.eval.run.claim guards any folder reused)
    if not OmegaConf.has_resolver("sdexp.pid"):
        OmegaConf.register_new_resolver("sdexp.pid", lambda: str(os.getpid()))
    # ${sdexp.count:drone.rotors} in conf/drone/custom.yaml: as many rotors as drone.rotors lists
    if not OmegaConf.has_resolver("sdexp.count"):
        OmegaConf.register_new_resolver("sdexp.count", lambda key, *, _root_: len(OmegaConf.select(_root_, key) or []))


def _nonfinite(value: Any) -> bool:
    """True when ``value`` (a number or a sequence of them) holds a nan or an infinity."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return False
    if isinstance(value, (int, float)):
        return not math.isfinite(value)
    if isinstance(value, (list, tuple, ListConfig)):
        return any(_nonfinite(v) for v in value)
    return False


def check_range(ok: bool, key: str, value: Any, allowed: str) -> None:
    """A range that depends on more than the key itself (sdexp.ranges declares the others on
    their fields), in the same words. ``inf`` passes ``> 0`` and ``nan`` fails every comparison:
    a non-finite number is always out of range here, whatever ``ok`` says."""
    if not ok or _nonfinite(value):
        raise UserError(f"{key} = {value!r} is out of range: allowed {allowed}")


# ------------------------------------------------------------------ the shape of the config

# Upper bound on the elements a drone's mesh may have, estimated before meshing from its bounding
# box: fTetWild and Triangle take minutes (or fail) beyond it, and no experiment needs it.
MAX_ELEMENTS = 300_000
MIN_ELEMENTS_ALONG = 4   # elements along the drone's longest side: fewer meshes another body


def _fields(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _schema_error(key: str, names: list[str], where: str) -> UserError:
    prefix = key.rsplit(".", 1)[0] + "." if "." in key else ""
    hint = did_you_mean(key.rsplit(".", 1)[-1], names, prefix)
    return UserError(f"{key} is not a config key{hint}: the keys of {where} are {', '.join(sorted(names))}")


def _walk_schema(node: DictConfig, cls, prefix: str) -> None:
    hints = _fields(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for key in node.keys():
        if key not in names:
            raise _schema_error(f"{prefix}{key}", names, prefix[:-1] or "the config")
    for name in names:
        if OmegaConf.is_missing(node, name):
            continue
        value = node._get_node(name)
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(value, DictConfig) and not value._is_none():
            _walk_schema(value, hint, f"{prefix}{name}.")
        elif typing.get_origin(hint) in (list, List) and isinstance(value, ListConfig) and not value._is_none():
            (item,) = typing.get_args(hint) or (Any,)
            if dataclasses.is_dataclass(item):
                for i, v in enumerate(value):
                    if isinstance(v, DictConfig):
                        _walk_schema(v, item, f"{prefix}{name}[{i}].")


def check_schema(node: dict | DictConfig, cls, prefix: str) -> None:
    """Every key of ``node`` (plain or composed) is a field of the dataclass ``cls``, nested ones
    too; the error names the key as ``prefix`` + key, the closest valid one and the valid ones."""
    _walk_schema(node if isinstance(node, DictConfig) else OmegaConf.create(node), cls, prefix)


def unknown_key_error(key: str) -> UserError | None:
    """The error for an override of ``key`` that the schema has no place for (None when the key's
    parent is not a schema node, e.g. a free-form params mapping)."""
    cls, parts = Config, key.split(".")
    for i, part in enumerate(parts[:-1]):
        hint = _fields(cls).get(part)
        if not dataclasses.is_dataclass(hint):
            return None if hint is not None else _schema_error(
                ".".join(parts[:i + 1]), [f.name for f in dataclasses.fields(cls)],
                ".".join(parts[:i]) or "the config")
        cls = hint
    return _schema_error(key, [f.name for f in dataclasses.fields(cls)], ".".join(parts[:-1]) or "the config")


def unknown_param_error(key: str, params_cls, experiment: str) -> UserError:
    """The error for ``experiment.params.<key>``, which the experiment's params (``params_cls``,
    sdexp.experiment_params) lack: the closest one and all of them."""
    cls, parts = params_cls, key.split(".")
    for i, part in enumerate(parts[:-1]):   # a nested key (beam.lenght): the nested dataclass's fields
        hint = _fields(cls).get(part) if cls is not None else None
        if not dataclasses.is_dataclass(hint):
            parts = [".".join(parts[:i + 1])]   # the first part that is not a group is the unknown one
            break
        cls = hint
    parent, name = ".".join(parts[:-1]), parts[-1]
    names = sorted(f.name for f in dataclasses.fields(cls)) if cls is not None else []
    hint = did_you_mean(name, names, f"experiment.params.{parent + '.' if parent else ''}")
    what = f"of {experiment}" if not parent else f"of {experiment}'s {parent}"
    return UserError(f"experiment.params.{key} is not a parameter {what}{hint}: allowed {', '.join(names) or 'none'}")


def check_keys(cfg: DictConfig) -> None:
    """Every key must be in the schema: Hydra's ``+key=value`` appends past a struct config (the
    form Hydra itself suggests after a misspelled override), so a typo given that way is caught
    here, with the closest valid key. experiment.params is checked against the schema its
    experiment placed there."""
    _walk_schema(cfg, Config, "")
    params = cfg.experiment._get_node("params")
    cls = OmegaConf.get_type(params) if isinstance(params, DictConfig) else None
    if dataclasses.is_dataclass(cls):
        for key in params.keys():
            if key not in {f.name for f in dataclasses.fields(cls)}:
                raise unknown_param_error(str(key), cls, cfg.experiment.name)
        _walk_schema(params, cls, "experiment.params.")


def check_complete(cfg: DictConfig) -> None:
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise UserError(f"{missing[0]} has no value (???): set it, e.g. {missing[0]}=<value>"
                        + (f" (also unset: {', '.join(missing[1:])})" if len(missing) > 1 else ""))


def check_finite(node: Any, prefix: str = "") -> None:
    """Every number anywhere in the config (effects' and shapes' params included) is finite."""
    if isinstance(node, DictConfig):
        items = [(f"{prefix}{k}", node._get_node(k)) for k in node.keys()]
    elif isinstance(node, ListConfig):
        items = [(f"{prefix[:-1]}[{i}]", node._get_node(i)) for i in range(len(node))]
    else:
        return
    for key, child in items:
        if isinstance(child, (DictConfig, ListConfig)):
            check_finite(child, f"{key}.")
            continue
        value = child._value() if hasattr(child, "_value") else child
        if isinstance(value, str) and value.strip().lower().lstrip("+-") in ("inf", "nan", "infinity"):
            value = float(value)
        if _nonfinite(value):
            raise UserError(f"{key} = {value!r} is not a finite number")


def validate(cfg: DictConfig | Config) -> None:
    """Raise UserError naming the first key whose value is outside its physical range: the
    ranges the schema's fields declare (sdexp.ranges), then what depends on two keys at once."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.structured(cfg)
    check_keys(cfg)
    try:
        OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
        check_complete(cfg)
    except OmegaConfBaseException as err:   # an interpolation that does not resolve
        key = getattr(err, "full_key", None)
        raise UserError(f"{key}: {one_line(err)}" if key else one_line(err)) from None
    check_fields(cfg, Config)
    _check_drone(cfg.drone)
    _check_sim(cfg)
    _check_learning(cfg.data)
    for key, bad in (("sim.ground", cfg.sim.ground is not None), ("sim.mass_scaling", cfg.sim.mass_scaling > 0)):
        # what the reduced model refuses, named for the key that put the data on it
        check_range(cfg.data.sim_model != "reduced" or not bad, "data.sim_model", cfg.data.sim_model,
                    f"null or full while {key} is set (the reduced model cannot carry it)")
    _check_control(cfg)
    check_finite(cfg)   # what no range names: sim.ground, effects' and shapes' params, ...


def _check_drone(d) -> None:
    """The drone's design and a mesh whose size is neither absurd nor degenerate."""
    if d.shape == "file" and d.mesh.file is None:   # drone=custom as it stands: the template
        raise UserError(f"drone.mesh.file has no value: drone {d.name} is made from a mesh file, e.g. "
                        "drone.mesh.file=body.stl 'drone.rotors=[[x,y,z],...]' (README, Your own drone)")
    if d.mesh.file is None:
        check_range(d.num_rotors >= 1, "drone.num_rotors", d.num_rotors, ">= 1")
        check_range(len(d.size) == d.dim, "drone.size", list(d.size), f"{d.dim} positive lengths")
        check_range(all(x > 0 for x in d.size), "drone.size", list(d.size), "all lengths > 0")
        for key in ("rotors", "rotor_normals", "imus"):
            check_range(not getattr(d, key), f"drone.{key}", list(getattr(d, key)),
                        "[] unless drone.mesh.file is set (the built-in shapes place their own)")
        check_edge_length(d, list(d.size))   # a drone from a file: its size is the file's (sim.checks)
    check_range(not d.mesh.mirror or (d.dim == 3 and len(set(d.mesh.mirror)) == len(d.mesh.mirror)
                                 and set(d.mesh.mirror) <= {"x", "z"}),
                "drone.mesh.mirror", list(d.mesh.mirror), "a list of distinct planes x, z (3D drones only)")
    check_range(d.mesh.layers == 0 or (d.dim == 3 and 1 <= d.mesh.layers <= 8), "drone.mesh.layers", d.mesh.layers,
                "0 (fTetWild) or 1-8 layers through the thickness (3D drones only)")
    check_range(d.mesh.outline in ("resampled", "exact") and (d.mesh.outline == "resampled" or d.mesh.layers),
                "drone.mesh.outline", d.mesh.outline, "resampled, or exact with drone.mesh.layers >= 1")


def check_edge_length(d, size: list[float]) -> None:
    """drone.mesh.edge_length between the size that gives about MAX_ELEMENTS elements in the
    body's bounding box and the one that gives MIN_ELEMENTS_ALONG along its longest side."""
    longest = max(float(x) for x in size)
    box = math.prod(float(x) for x in size)
    # elements in the bounding box at this edge length: regular tets (edge^3 / 6 sqrt 2) or triangles
    unit = 1 / (6 * math.sqrt(2)) if d.dim == 3 else math.sqrt(3) / 4
    finest = (box / (unit * MAX_ELEMENTS)) ** (1 / d.dim)
    coarsest = longest / MIN_ELEMENTS_ALONG
    check_range(finest <= d.mesh.edge_length <= coarsest, "drone.mesh.edge_length", d.mesh.edge_length,
                f"in [{finest:.3g}, {coarsest:.3g}] m for this {d.name} (at least {MIN_ELEMENTS_ALONG} elements "
                f"along its {longest:g} m, at most about {MAX_ELEMENTS:,} elements)")


def _check_sim(cfg) -> None:
    """The substep within the control step, the seed, the obstacles."""
    d, s = cfg.drone, cfg.sim
    check_range(s.substep is None or 0 < s.substep <= s.control_dt, "sim.substep", s.substep,
                "null or in (0, sim.control_dt]")
    if not isinstance(cfg.seed, bool) and isinstance(cfg.seed, int) and not 0 <= cfg.seed < 2 ** 32:
        raise UserError(f"seed = {cfg.seed} is out of range: allowed 0 to {2 ** 32 - 1}")
    for i, b in enumerate(s.obstacles):
        check_range(len(b.min) == len(b.max) == d.dim and all(a < c for a, c in zip(b.min, b.max)),
                    f"sim.obstacles[{i}]", OmegaConf.to_container(b) if isinstance(b, DictConfig) else b,
                    f"min < max, {d.dim} coordinates each")


def _check_learning(a) -> None:
    """The data recipe's ranges that depend on each other."""
    check_range(len(a.thrust_range) == 2 and -1 <= a.thrust_range[0] < a.thrust_range[1] <= 1, "data.thrust_range",
                list(a.thrust_range), "[lo, hi] with -1 <= lo < hi <= 1 (fractions of drone.max_thrust)")
    check_range(a.episode_seconds >= a.hold_seconds, "data.episode_seconds", a.episode_seconds, ">= data.hold_seconds")
    check_range(a.hover == "rigid" or a.around_hover, "data.hover", a.hover,
                "rigid unless data.around_hover = true (shape names the centre of a draw around hover)")


def _check_control(cfg) -> None:
    """The controllers' options that depend on the drone or on each other."""
    c = cfg.control
    check_range(c.q_p_axes is None or (len(c.q_p_axes) == cfg.drone.dim and all(v > 0 for v in c.q_p_axes)),
                "control.q_p_axes", c.q_p_axes, f"null or {cfg.drone.dim} numbers > 0 (one per axis of drone {cfg.drone.name})")
    n_e = 3 if cfg.drone.dim == 3 else 1
    check_range(c.q_e_axes is None or (len(c.q_e_axes) == n_e and all(v > 0 for v in c.q_e_axes)),
                "control.q_e_axes", c.q_e_axes, f"null or {n_e} numbers > 0 (one per Euler angle of drone {cfg.drone.name})")
    check_range(c.share_pull == 0 or not c.feedforward, "control.share_pull", c.share_pull,
                "0 while control.feedforward is on (the feed-forward sets the operating thrust itself)")
    check_range(c.approach_speed is None or c.waypoint_max is not None, "control.approach_speed", c.approach_speed,
                "null while control.waypoint_max is null (the approach starts where the waypoint is bounded)")
    check_range(c.delay_phase_deg is None or cfg.model.command_delay > 0, "control.delay_phase_deg",
                c.delay_phase_deg, "null while model.command_delay is 0 (there is no delay to bound)")
