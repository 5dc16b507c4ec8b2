"""The schema of ``experiment.params``: one dataclass per experiment, with its defaults, types
and allowed ranges. Each conf/experiment/<name>.yaml places its dataclass at experiment.params
(``- /experiment_params@experiment.params: <name>`` in its defaults list), so Hydra composes the
defaults into the config, refuses a key the dataclass lacks or a value of the wrong type, and
``OmegaConf.to_object`` at the runner boundary (sdexp.eval.run.typed) hands the runner an instance,
whose ``__post_init__`` checks the ranges.

A field's ``metadata`` says what is allowed beyond its type: ``range`` (sdexp.ranges: a
predicate and its text, applied to every number of a list or mapping) and ``names`` (every value must name one
of those: an option of that config group, a drone or an experiment, with "controller" a
registered controller, with "effect" an effect of the library; checked where the configs and the
registries are known, before the conversion: sdexp.eval.run.check_names).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional

from hydra.core.config_store import ConfigStore

from sdexp.config import ELEMENTS, MODELS
from sdexp.errors import UserError
from sdexp.ranges import at_least, between, check_fields, choices, nonnegative, param, positive, ranged

PREFIX = "experiment.params."


def _param(default, ok: Callable[[Any], bool] | None = None, allowed: str = "", **metadata) -> Any:
    """A field with ``default`` and its range (sdexp.ranges: the one declaration the config and
    the effects use too)."""
    return param(default, ranged(ok, allowed, **metadata) if ok is not None else metadata)


def drone_choice(default):
    """A drone name, or a list of them (null: every drone, where the runner says so)."""
    return _param(default, names="drone")


def controller_choice(default):
    """A list of controller names (sdexp.eval.controllers.CONTROLLERS)."""
    return _param(default, names="controller")


@dataclass
class Params:
    """What every experiment's params share: range checks on construction (``to_object``)."""

    def __post_init__(self) -> None:
        check_fields(self, type(self), PREFIX)
        self.check()

    def check(self) -> None:
        """Rules between fields (none by default)."""


# ------------------------------------------------------------------ the paper's experiments

@dataclass
class SotaParams(Params):
    seconds: float = param(20.0, positive())
    start: List[float] = _param([0.0, 0.0, 0.0])
    target: List[float] = _param([3.0, 3.0, 3.0])
    controllers: List[str] = controller_choice(["ours", "rigid_lqr", "geometry_lqr", "neural"])
    animate: List[str] = controller_choice(["ours"])   # controllers whose flight is also drawn: sota_<name>.mp4 ([]: none)
    paraview: bool = False   # true: also <name>_vtu/<name>.pvd, the mesh per frame for ParaView (about 3 MB a second)

    def check(self) -> None:
        stray = [c for c in self.animate if c not in self.controllers]
        if stray:
            raise UserError(f"{PREFIX}animate = {self.animate!r}: {stray[0]!r} is not flown: allowed a list of the "
                            f"controllers in {PREFIX}controllers ({', '.join(self.controllers) or 'none'})")


@dataclass
class NsweepParams(Params):
    seconds: float = param(20.0, positive())
    start: List[float] = _param([0.0, 0.0, 0.0])
    target: List[float] = _param([3.0, 3.0, 3.0])
    n_values: List[int] = _param([1, 2, 5, 10, 20, 30, 40, 50, 100], lambda v: v > 0, "> 0")


@dataclass
class AblationFixedPointParams(Params):
    seconds: float = param(10.0, positive())
    distance: float = param(2.0, positive())
    noise_levels: List[float] = _param([0.0, 0.1, 0.2, 0.3, 0.4, 0.8], lambda v: v >= 0, ">= 0")
    trials: int = param(4096, positive())        # random (s, u) tried before the gradient descent
    descent_steps: int = param(2000, positive())


@dataclass
class HoverDeformParams(Params):
    angle_deg: float = 15.0             # petal raise (the paper does not state it)
    settle_seconds: float = param(2.0, nonnegative())   # after release; the paper measures "ever since the initial drop"
    ramp_seconds: float = param(2.0, positive())
    hold_seconds: float = param(3.0, nonnegative())
    animate: bool = True                # also hover_deform.mp4 (the deforming drone)
    paraview: bool = False   # true: also <name>_vtu/<name>.pvd, the mesh per frame for ParaView (about 3 MB a second)


@dataclass
class ObstacleParams(Params):
    seconds: float = param(15.0, positive())
    velocity: List[float] = _param([0.4, 0.2, 0.0])   # m/s, the goal position moves with it
    fold_deg: float = 75.0              # the paper's star raised its wings by over 73 deg
    fold_start: float = param(1.0, nonnegative())
    fold_seconds: float = param(2.0, positive())
    animate: bool = True                # also obstacle.mp4 (the drone and the blocks)
    paraview: bool = False   # true: also <name>_vtu/<name>.pvd, the mesh per frame for ParaView (about 3 MB a second)


FLEET_TASKS = ("hover", "reach", "velocity", "deform")   # the paper's four tasks (section 5)
FLEET_CONTROLLERS = ("ours", "rigid_lqr", "geometry_lqr", "reduced_lqr")   # the neural controller needs its own training


@dataclass
class FleetParams(Params):
    """sdexp.eval.fleet: every drone of ``drones`` learned and flown through ``tasks``."""
    drones: Optional[List[str]] = drone_choice(None)   # null = all twelve
    tasks: List[str] = _param(list(FLEET_TASKS))
    controllers: List[str] = controller_choice(["ours", "rigid_lqr"])
    # each its own data, nets and noise; five, as the paper's claim is counted (a pair flies when every seed does)
    seeds: List[int] = _param([0, 1, 2, 3, 4], lambda v: v >= 0, ">= 0")
    # the data rule: samples = samples_per_channel x the drone's state channels (n_s + n_e + dim:
    # bends, attitude, position; each comes with its rate), at least min_samples (docs/results.md
    # "Fleet" has the learning curve behind the numbers); null: data.samples for every drone
    samples_per_channel: Optional[int] = param(1500, positive())
    min_samples: int = param(8000, positive())
    hover_seconds: float = param(10.0, positive())
    reach_seconds: float = param(10.0, positive())
    reach_lengths: float = param(1.0, positive())    # the trip, diagonal, in body lengths (the largest size)
    speed: float = param(0.5, positive())            # m/s, commanded along +x
    ramp_seconds: float = param(2.0, nonnegative())  # the goal velocity grows from 0 to speed, ...
    velocity_seconds: float = param(10.0, positive())   # ... then is held this long
    # the deform task's bend target for the odd sensors (1, 3, ...), held, then released: the body's
    # own reach (statics.deform_reach) times deform_reach_share, at most deform_deg (the paper
    # states no amplitude); a target under the task's tolerance is beyond the body, not flown
    deform_deg: float = param(15.0, positive("deg"))
    deform_reach_share: float = param(0.5, between(0, 1, "(]"))
    settle_seconds: float = param(2.0, nonnegative())
    deform_ramp_seconds: float = param(1.0, positive())
    deform_hold_seconds: float = param(3.0, nonnegative())
    workers: int = param(2, positive())              # (drone, seed) jobs side by side, one core each
    # per drone, the learning and control keys it learns and flies with instead of the run's
    # (sdexp.eval.fleet.with_recipe, which checks them), e.g. {rod: {model: {linear: [d, g, h]}}}: the paper trains
    # each design on its own; the world (drone, sim, noise) and the tasks are the same for all
    recipes: Dict[str, Dict[str, Any]] = param({})

    def check(self) -> None:
        for key, value, allowed in (("tasks", self.tasks, FLEET_TASKS),
                                    ("controllers", self.controllers, FLEET_CONTROLLERS)):
            stray = [v for v in value if v not in allowed]
            if stray or not value:
                raise UserError(f"{PREFIX}{key} = {value!r}: allowed a non-empty list of {', '.join(allowed)}"
                                + (f" ({stray[0]!r} is none of them)" if stray else ""))
        if len(set(self.seeds)) != len(self.seeds):
            raise UserError(f"{PREFIX}seeds = {self.seeds!r}: allowed distinct seeds")


@dataclass
class ModelTestParams(Params):
    rollout_seconds: float = param(70.0, positive())   # test flight length; simulated when no held-out episode is this long
    relinearize_every: int = param(5, positive())      # control steps between Jacobians (5 = 20 Hz)
    horizon_seconds: float = param(1.0, positive())    # the short-horizon rollouts restart from the truth this often
    plot_seconds: float = param(5.0, positive())       # window of the acceleration overlay
    test_seed_offset: int = param(10000, nonnegative())  # the test flight's seed is seed + this (unseen thrust draws)
    flight_attempts: int = param(5, positive())        # a flight the simulator fails is retried with the next seed; the longest is kept


@dataclass
class AblationDecompositionParams(Params):
    raw_hidden: Optional[int] = param(None, positive())   # width of the undecomposed network; null = model.hidden


@dataclass
class BenchControlParams(Params):
    samples: int = param(200, positive())


# ------------------------------------------------------------------ the simulator's experiments

@dataclass
class BeamParams:
    """validate_fem's cantilever (sdexp.eval.validate_fem.Beam adds the beam theory)."""
    length: float = 1.5
    thickness: float = 0.225     # the flower's plate thickness
    width: float = 0.3           # 3D only
    youngs_modulus: float = 6000.0
    poisson_ratio: float = 0.3
    sag: float = 0.01            # Euler-Bernoulli static tip deflection / length (small: linear)


# The converged references' refinements, per dimension (drone.dim): in 3D, 1.5 / 2 / 3 reach
# 300k unknowns (the donut's finest ran 15 min at 11 GB in SuperLU and was stopped), 1 / 1.5 / 2
# fit in 16 min and 3.3 GB for all twelve; in 2D the 1x mesh is the drone's own and 1 / 1.5 / 2
# left the rod's reference unconverged (+-19%). docs/physics.md.
REFINE = {"2d": [1.5, 2.0, 3.0], "3d": [1.0, 1.5, 2.0]}


@dataclass
class ValidateFemParams(Params):
    layers: Dict[str, Dict[str, List[int]]] = _param(   # elements through the thickness, per element type and dimension
        {"linear": {"2d": [1, 2, 4, 8], "3d": [1, 2, 3, 4, 6]}, "quadratic": {"2d": [1, 2, 4], "3d": [1, 2, 3]}},
        lambda v: v > 0, "> 0")
    drone_edge_length: Optional[float] = param(0.25, positive())   # the flower's default mesh.edge_length
    beam: BeamParams = _param(BeamParams())
    drones: Optional[List[str]] = drone_choice(None)   # every drone (null) or a list: default mesh vs the converged body
    refine: Dict[str, List[float]] = _param(REFINE, lambda v: v > 0, "> 0")   # the converged reference: meshes this much finer
    bend_load: float = param(2.0, nonnegative())          # N on each outer rotor, over hover thrust


@dataclass
class BenchSimParams(Params):
    drones: Optional[List[str]] = drone_choice(None)   # null = all twelve, [] = none
    elements: List[str] = _param(list(ELEMENTS))
    seconds: float = param(3.0, positive())               # simulated seconds per drone
    scaling_drone: Optional[str] = drone_choice("flower")   # null = no refinement series
    scaling_edges: Dict[str, List[float]] = _param(   # mesh.edge_length of the series, per element type
        {"linear": [0.35, 0.25, 0.15, 0.1, 0.07],      # about 1.3k, 2k, 5k, 12k and 45k tets
         "quadratic": [0.6, 0.5, 0.35, 0.25, 0.15]}, lambda v: v > 0, "> 0")
    scaling_seconds: float = param(1.0, positive())
    resolution_factors: List[float] = _param([1.0, 1.4, 2.0])  # every drone's quadratic mesh at edge_length x these:
                                  # accuracy and substeps (no timing), the evidence behind each default resolution
    bend_load: float = param(2.0, nonnegative())   # N: the outer rotors' push (no net lift or tilting torque) of the accuracy load
    refine: Dict[str, List[float]] = _param(REFINE, lambda v: v > 0, "> 0")   # the converged reference: quadratic meshes at edge_length / these
    # sim.precision and sim.mass_scaling on these drones' default quadratic meshes (null or [] = none):
    # the force kernel and the whole step timed with the variants alternated, a noise-free flight and
    # an undamped free vibration of float32 against float64, the modes that scaling moves
    variants_drones: Optional[List[str]] = drone_choice(["flower"])
    variants_seconds: float = param(3.0, positive())      # simulated seconds of each variant's step timing
    deviation_seconds: float = param(5.0, positive())     # the noise-free float32 / float64 flight
    mass_scaling: float = _param(0.005, lambda v: 0 < v <= 0.1, "in (0, 0.1]")   # the scaled variants' budget
    # the simulators of the drone rows (sim.model's choices): a row per drone, element and model, the
    # models timed in one process block by block under the same holds; [full, reduced] adds the reduced
    # model (built with sim.reduced.*) beside the full one, with its speed-up (docs/speed.md)
    models: List[str] = param(["full"], choices(MODELS))

    def check(self) -> None:
        if not set(self.elements) <= set(ELEMENTS):
            raise UserError(f"{PREFIX}elements = {self.elements!r}: allowed a list of {', '.join(ELEMENTS)}")
        if not self.models or len(set(self.models)) != len(self.models):
            raise UserError(f"{PREFIX}models = {list(self.models)!r}: allowed a non-empty list of distinct models, "
                            f"each {' or '.join(MODELS)}")


@dataclass
class GalleryParams(Params):
    drones: Optional[List[str]] = drone_choice(None)   # null = all twelve


@dataclass
class BenchSweepParams(Params):
    experiment: str = _param("ablation_fixed_point", names="experiment")   # the swept experiment: the rod's cold run is about a minute
    seeds: int = param(5, nonnegative())
    jobs: List[int] = _param([1, 2], lambda v: v > 0, "> 0")   # jobs side by side; the first is the baseline of the speed-up
    overrides: List[str] = _param([])   # extra overrides for every job, e.g. ["drone=rod"]


# ------------------------------------------------------------------ the discrepancy workflow, sweeps

@dataclass
class RecordParams(Params):
    """None: the flights are discrepancy.record's."""


@dataclass
class DiscrepancyParams(Params):
    """None: the workflow's settings are the discrepancy group's."""


@dataclass
class DiscrepancyBenchParams(Params):
    """sdexp.discrepancy.bench; what needs the drone or the folders (rescore, scenario_dir, only)
    is checked by its check (sdexp.discrepancy.bench.check) before anything is written."""
    effects: Optional[List[str]] = _param(None, names="effect")   # null = the whole library
    # 0 moderate, 1 strong: the two strengths each effect's bench_strengths gives
    levels: List[int] = _param([0, 1], lambda v: v in (0, 1), "0 (moderate) or 1 (strong)")
    seeds: int = param(2, nonnegative())            # per effect and strength
    nulls: int = param(20, nonnegative())
    combos: bool = True
    variants: int = param(1, nonnegative())         # per seed: every outside-the-library effect with a fair library
                                           # answer (gusty wind at two strengths, per-rotor lags, a hanging weight)
    unmodelled: int = param(3, nonnegative())       # draws of every outside-the-library effect without one (five kinds,
                                           # sdexp.discrepancy.bench_effects): the honest answer is unexplained or
                                           # partly; one draw each resolves the honest share to 0.2 only
    workers: int = param(2, positive())
    rescore: bool = False                  # true: recompute the gap columns of an earlier run in the same folder
    scenario_dir: Optional[str] = None     # where each scenario's logs and reports go; null = <run dir>/scenarios
    only: Optional[List[str]] = None       # scenario ids to run, e.g. [payload-b0]; the others skipped, every draw unchanged

    def check(self) -> None:
        # a repeated effect or level would draw scenarios of the same id into one folder
        for key, value in (("effects", self.effects), ("levels", self.levels)):
            if value is not None and len(set(value)) != len(value):
                raise UserError(f"{PREFIX}{key} = {list(value)!r}: allowed distinct {key}")


@dataclass
class ReportParams(Params):
    sweep_dir: Optional[str] = "${sweep_dir}"   # the sweep folder to aggregate (required)
    confidence: float = _param(0.95, lambda v: 0 < v < 1, "in (0, 1)")   # of the two-sided Student-t interval
    # two metrics, [x, y], and optionally a boolean third that fills a point where true: scatter.png, one
    # point per job, a colour per group, e.g. [wing_pitch_change_deg, max_z_deviation_m, passed]
    scatter: Optional[List[str]] = None
    scatter_lines: Optional[List[Optional[float]]] = None   # dashed at x = [0] and y = [1] (null: none), e.g. [73, 0.05]

    def check(self) -> None:
        for key, value, sizes, what in (("scatter", self.scatter, (2, 3), "[x, y] or [x, y, a boolean metric]"),
                                        ("scatter_lines", self.scatter_lines, (2,), "[x or null, y or null]")):
            if value is not None and len(value) not in sizes:
                raise UserError(f"{PREFIX}{key} = {list(value)!r}: allowed {what}, or null")


@dataclass
class ReducedGatesParams(Params):
    drones: Optional[List[str]] = drone_choice(None)   # null = all twelve, [] = none (the frontier alone)
    recipes: List[str] = param(["near_hover", "paper"], choices(("near_hover", "paper")))   # held-out flights' recipes
    flight_seeds: List[int] = _param([1001], lambda v: v >= 0, ">= 0")   # held out: the snapshots use seeds 0 and 1
    flight_seconds: float = param(5.0, positive("s"))
    energy_seconds: float = param(1.0, positive("s"))
    bend_load: float = param(2.0, nonnegative())   # N: validate_fem's load on the outer rotors
    frontier_drone: Optional[str] = drone_choice("flower")   # null = no frontier
    # [basis, modal_derivatives, cubature] points of the frontier (sim.reduced's other keys as set)
    frontier: List[List[int]] = _param([[32, 2, 100], [48, 4, 150], [96, 6, 300], [128, 8, 400]], lambda v: v >= 0, ">= 0")
    workers: int = param(2, at_least(1))   # drones built and flown side by side


@dataclass
class DesignRuleParams(Params):
    """sdexp.eval.design_rule: per drone, the candidates of its open design (``grid``: thickness or a
    proportion of its shape (drone.params) -> values; every combination) and the drawing the rule
    stays nearest (``drawn``: key -> value; a key not given: the drone config's own)."""
    designs: Dict[str, Dict[str, Any]] = param({})
    drones: Optional[List[str]] = drone_choice(None)   # which of designs (null: all of them)
    seconds: float = param(10.0, positive("s of static hover held"))
    workers: int = param(2, at_least(1))

    def check(self) -> None:
        if not self.designs:   # the drones' names: sdexp.eval.design_rule.check, where the configs are known
            raise UserError(f"{PREFIX}designs is empty: give at least one drone's grid")
        for name, design in self.designs.items():
            where = f"{PREFIX}designs.{name}"
            stray = [k for k in design if k not in ("grid", "drawn")]
            grid = design.get("grid") or {}
            if stray or not grid or not all(isinstance(v, (list, tuple)) and len(v) for v in grid.values()):
                raise UserError(f"{where} = {dict(design)!r}: allowed grid (key -> a non-empty list of "
                                f"values) and drawn (key -> value)")
        stray = [n for n in self.drones or [] if n not in self.designs]
        if stray:
            raise UserError(f"{PREFIX}drones = {self.drones!r}: {stray[0]!r} has no design to choose: choose "
                            f"among {', '.join(self.designs)}")


# kernel choice -> the environment of its fleet's process: OpenBLAS's kernel (numpy's linear algebra)
# and MKL's code path (torch's); "machine": what this CPU picks
KERNELS = {"machine": {}, "haswell": {"OPENBLAS_CORETYPE": "Haswell"}, "zen": {"OPENBLAS_CORETYPE": "Zen"},
           "sandybridge": {"OPENBLAS_CORETYPE": "Sandybridge"}, "prescott": {"OPENBLAS_CORETYPE": "Prescott"},
           "skylakex": {"OPENBLAS_CORETYPE": "SkylakeX"}, "mkl_avx2": {"MKL_CBWR": "AVX2"},
           "mkl_compatible": {"MKL_CBWR": "COMPATIBLE"},
           "haswell_mkl_avx2": {"OPENBLAS_CORETYPE": "Haswell", "MKL_CBWR": "AVX2"}}

@dataclass
class KernelSpreadParams(Params):
    """sdexp.eval.kernel_spread: one fleet per BLAS kernel choice, each learning afresh."""
    # the fleet each kernel choice flies: sdexp experiment=fleet <these>
    overrides: List[str] = _param(["experiment.params.drones=[flower,tripod]", "experiment.params.seeds=[0]",
                                   "experiment.params.controllers=[ours]"])
    # which kernel choices (sdexp.eval.kernel_spread.KERNELS: the environment of each fleet's process)
    kernels: List[str] = param(["machine", "haswell", "sandybridge", "prescott", "mkl_avx2", "haswell_mkl_avx2"],
                               choices(KERNELS))
    # cache kinds every fleet reads from the run's cache instead of making them again: made by the
    # mesher and the C simulator, not by the BLAS libraries (the data, nets and reduced models are not)
    shared: List[str] = param(["mesh2d", "mesh3d", "bodyphysics", "statichover", "shapehover", "kernels"],
                              choices(("mesh2d", "mesh3d", "bodyphysics", "statichover", "shapehover", "kernels",
                                       "massscale")))
    workers: int = param(2, at_least(1))   # fleets side by side, one core each

    def check(self) -> None:
        if not self.kernels or len(set(self.kernels)) != len(self.kernels):
            raise UserError(f"{PREFIX}kernels = {list(self.kernels)!r}: allowed a non-empty list of distinct names")


# ------------------------------------------------------------------ the researcher's toolbox

RL_TASKS = ("hover", "reach")   # the environments' presets (sdexp.envs.tasks): the paper's SOTA task and a hover
RL_ALGORITHMS = ("sac", "ppo")


@dataclass
class RlBaselineParams(Params):
    """sdexp.envs.rl_baseline: a Stable-Baselines3 agent beside ours at equal data."""
    tasks: List[str] = param(["hover", "reach"], choices(RL_TASKS))
    algorithm: str = param("sac", choices(RL_ALGORITHMS))   # SAC: the sample-efficient one, for equal data
    # environment transitions at which the agent is scored: checkpoints of one training run each
    budgets: List[int] = param([60000, 600000], positive("transitions"))
    seeds: List[int] = _param([0, 1, 2], lambda v: v >= 0, ">= 0")   # each: ours' data and nets, the agent's training
    episodes: int = param(3, positive("episodes"))   # scored per checkpoint (and for ours), on sim.model
    workers: int = param(2, at_least(1))   # (task, seed) trainings side by side, one core each

    def check(self) -> None:
        for key, value in (("tasks", self.tasks), ("budgets", self.budgets), ("seeds", self.seeds)):
            if not value or len(set(value)) != len(value):
                raise UserError(f"{PREFIX}{key} = {list(value)!r}: allowed a non-empty list of distinct values")


# experiment name (its conf/experiment/<name>.yaml) -> the schema of its params
PARAMS: dict[str, type[Params]] = {
    "ablation_decomposition": AblationDecompositionParams, "ablation_fixed_point": AblationFixedPointParams,
    "bench_control": BenchControlParams, "bench_sim": BenchSimParams, "bench_sweep": BenchSweepParams,
    "design_rule": DesignRuleParams,
    "discrepancy": DiscrepancyParams, "discrepancy_bench": DiscrepancyBenchParams, "fleet": FleetParams, "gallery": GalleryParams,
    "hover_deform": HoverDeformParams, "kernel_spread": KernelSpreadParams, "model_test": ModelTestParams, "nsweep": NsweepParams,
    "obstacle": ObstacleParams, "record": RecordParams, "reduced_gates": ReducedGatesParams,
    "report": ReportParams, "rl_baseline": RlBaselineParams, "sota": SotaParams,
    "validate_fem": ValidateFemParams,
}
GROUP = "experiment_params"


def names(params_cls: type) -> list[str]:
    return sorted(f.name for f in dataclasses.fields(params_cls))


def register() -> None:
    cs = ConfigStore.instance()
    for name, cls in PARAMS.items():
        cs.store(group=GROUP, name=name, node=cls)
