"""The fleet experiment: a reduced fleet (two small drones, tiny data, short flights) against its
stored reference, resuming from its job files, a drone that cannot learn recorded as a row, its
data rule and task schedules, the physics it reports, and its bad input."""
import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from sdexp.errors import UserError
from sdexp.eval import fleet
from sdexp.eval.run import run_experiment
from sdexp.experiment_params import FleetParams
from tests.eval.references import REFERENCE_DIR, compare, reduced_overrides
from tests.conftest import make_cfg, make_config


def reduced(cache_dir, *extra):
    return make_cfg(*reduced_overrides("fleet", cache_dir), *extra)


def test_a_reduced_fleet_flies_every_task_and_matches_its_reference(tmp_path, cache_dir):
    m = run_experiment(reduced(cache_dir), tmp_path)
    assert compare("fleet", m, json.loads((REFERENCE_DIR / "fleet.json").read_text())) == []
    table = pd.read_csv(tmp_path / "fleet.csv")
    assert len(table) == 2 * 4 * 2   # drones x tasks x controllers, one seed
    assert set(table["task"]) == {"hover", "reach", "velocity", "deform"}
    assert set(table["controller"]) == {"ours", "rigid_lqr"}
    assert {"survived", "failure", "final_error", "velocity_error_rms", "max_tilt_deg", "bend_rms_deg"} <= set(table)
    physics = pd.read_csv(tmp_path / "physics.csv")
    assert list(physics["drone"]) == ["rod", "engine"] and (physics["d_val_rel_l1"] > 0).all()
    assert (physics[["model_accel_at_hover", "model_tilt_accel_at_hover", "model_torque_map_error",
                     "model_accel_error_at_release", "model_tilt_accel_error_at_release"]] >= 0).all().all()
    assert (physics[["data_torque_map_error_sent", "data_torque_map_error_acting", "data_level_transitions"]] >= 0).all().all()
    assert (tmp_path / "fleet.png").exists() and m["jobs"] == 2 and m["jobs_failed"] == 0
    # the engine (steel-stiff beside the rod) bends under 2 deg: its deform target, half of that, is
    # under the 5 deg tolerance, so not flown; the rod's is the task's 15 deg
    deform = table[table["task"] == "deform"].set_index(["drone", "controller"])
    assert (deform.loc["engine", "outcome"] == "beyond the body").all() and deform.loc["engine", "failure"].str.contains("deg").all()
    assert (deform.loc["rod", "target_deg"] == 15.0).all() and (deform.loc["rod", "outcome"] != "beyond the body").all()
    assert (physics["design_rule"] == "holds").all() and (physics["static_hover_share"] < 0.6).all()
    assert m["wall_seconds"] > 0
    # the reach task is a diagonal trip of one body length (the rod: 8 m long)
    reach = table[(table["drone"] == "rod") & (table["task"] == "reach")]
    assert reach["tolerance"].iloc[0] == pytest.approx(0.1 * 8.0)


def test_an_interrupted_fleet_resumes_with_the_jobs_it_has(tmp_path, cache_dir):
    first = run_experiment(reduced(cache_dir), tmp_path)
    before = pd.read_csv(tmp_path / "fleet.csv")
    (tmp_path / "metrics.json").unlink()                 # as if killed before the end ...
    (tmp_path / "jobs" / "engine_seed0.json").unlink()   # ... with the engine's job unfinished
    rod = tmp_path / "jobs" / "rod_seed0.json"           # and the rod's written before deform_reach_deg
    job = json.loads(rod.read_text())
    reach = job["physics"].pop("deform_reach_deg")
    shaped = job["physics"].pop("shape_hover_fold_deg")
    rod.write_text(json.dumps(job))
    again = run_experiment(reduced(cache_dir), tmp_path)
    filled = json.loads(rod.read_text())["physics"]
    assert filled["deform_reach_deg"] == pytest.approx(reach) and filled["shape_hover_fold_deg"] == pytest.approx(shaped)
    assert first["jobs_run"] == 2 and again["jobs_run"] == 1
    assert again["invocations"] == 2 and again["wall_seconds"] > first["wall_seconds"]   # both calls' wall time
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "fleet.csv"), before)   # flights repeat bit for bit


def test_a_drone_that_cannot_learn_is_a_recorded_row_and_the_fleet_goes_on(tmp_path, cache_dir, monkeypatch):
    from sdexp.eval import flights
    real = flights.Setup

    def setup(cfg, progress=True):
        if cfg.drone.name == "engine":
            raise RuntimeError("the data blew up")
        return real(cfg, progress)
    monkeypatch.setattr(flights, "Setup", setup)
    m = run_experiment(reduced(cache_dir), tmp_path)
    table = pd.read_csv(tmp_path / "fleet.csv")
    engine = table[table["drone"] == "engine"]
    assert len(engine) == 1 and not engine["survived"].iloc[0]
    assert "learning" in engine["failure"].iloc[0] and "the data blew up" in engine["failure"].iloc[0]
    assert len(table[table["drone"] == "rod"]) == 8 and m["jobs_failed"] == 1
    assert (tmp_path / "fleet.png").exists()


def test_a_fleet_where_no_drone_flies_is_still_a_table_of_reasons(tmp_path, cache_dir, monkeypatch):
    from sdexp.eval import flights

    def setup(cfg, progress=True):
        raise RuntimeError(f"the {cfg.drone.name}'s data blew up")
    monkeypatch.setattr(flights, "Setup", setup)
    m = run_experiment(reduced(cache_dir), tmp_path)
    table = pd.read_csv(tmp_path / "fleet.csv")
    assert list(table["drone"]) == ["rod", "engine"] and not table["survived"].any()
    assert {"primary", "primary_value", "tolerance"} <= set(table) and m["jobs_failed"] == 2
    assert (tmp_path / "fleet.png").exists()


def test_the_reach_trip_of_a_drone_from_a_mesh_file_is_its_rest_shape_long():
    """A paper drone's body length is its design's (drone.size); a drone of one's own has none
    given, so its rest shape's bounding box sets the trip."""
    from types import SimpleNamespace as NS
    rest = np.array([[0.0, 0.0, 0.0], [2.4, 0.2, -0.5], [1.0, 0.1, 2.0]])
    own = NS(cfg=NS(drone=NS(size=[])), drone=NS(fem=NS(rest=rest)))
    assert fleet.body_length(own) == pytest.approx(2.5)
    assert fleet.body_length(NS(cfg=NS(drone=NS(size=[3.6, 0.225, 3.6])), drone=None)) == 3.6


def test_the_data_rule_scales_with_the_state_channels():
    p = FleetParams()
    # flower: 8 bends + 3 angles + 3 positions; rod (2D): 8 + 1 + 2
    assert fleet.samples_for(p, 8, 3, 60000) == 1500 * 14
    assert fleet.samples_for(p, 8, 2, 60000) == 1500 * 11
    assert fleet.samples_for(p, 1, 2, 60000) == p.min_samples     # a small drone gets the floor
    assert fleet.samples_for(FleetParams(samples_per_channel=None), 8, 3, 60000) == 60000


def test_the_deform_task_bends_the_odd_sensors_then_releases_them():
    p = FleetParams(settle_seconds=2.0, deform_ramp_seconds=1.0, deform_hold_seconds=3.0, deform_deg=15.0)
    times, targets, seconds = fleet.deform_schedule(4, p, fleet.deform_target(p, 120.0))
    assert seconds == pytest.approx(10.0) and times == [0.0, 2.0, 3.0, 6.0, 7.0, 10.0]
    up = np.deg2rad(15.0)
    np.testing.assert_allclose(targets[2], [up, 0, up, 0])
    np.testing.assert_allclose(targets[-1], 0.0)


def test_the_velocity_task_ramps_and_the_reach_task_is_diagonal(cache_dir):
    cfg = make_config("experiment=fleet", "drone=flower")

    class FakeLayout:
        dim, n_s = 3, 8

    class FakeSetup:
        layout = FakeLayout()
        drone = None   # the reach trip reads the drone's size from its config

        def __init__(self):
            self.cfg = cfg

        def task(self, start, target, seconds, **kw):
            from sdexp.control.tasks import Task
            return Task(start=start, target=target, seconds=seconds, n_s=8, **kw)
    tasks = fleet.tasks_for(FakeSetup(), cfg.experiment.params, 120.0)
    reach, _ = tasks["reach"]
    assert np.linalg.norm(reach.target) == pytest.approx(3.6) and np.ptp(reach.target) == 0   # one body length
    velocity, since = tasks["velocity"]
    assert since == 2.0 and velocity.seconds == 12.0
    np.testing.assert_allclose(velocity.goal(12.0).p_dot, [0.5, 0, 0])


def test_physics_of_a_body_its_thrust_to_weight_and_a_fold_inverse_in_the_modulus(cache_dir):
    """The engine's hover fold is small (linear elasticity): doubling the modulus halves it."""
    from dataclasses import replace

    from sdexp.sim.drone import build_drone
    cfg = make_config("drone=engine")
    soft = fleet.physics_of(build_drone(cfg.drone, cache_dir, "quadratic"), cfg.sim, hold_seconds=1.0)
    stiff_cfg = replace(cfg.drone, youngs_modulus=2 * cfg.drone.youngs_modulus)
    stiff = fleet.physics_of(build_drone(stiff_cfg, cache_dir, "quadratic"), cfg.sim, hold_seconds=1.0)
    assert soft["thrust_to_weight"] == pytest.approx(6 * 10.0 / 9.81, rel=1e-6)
    assert soft["lift_tilt_rank"] == soft["lift_tilt_needed"] == 2
    assert 0 < soft["hover_fold_deg"] < 1
    assert stiff["hover_fold_deg"] == pytest.approx(soft["hover_fold_deg"] / 2, rel=0.15)
    assert 0 < soft["deform_reach_deg"] < 15      # the deform task's 15 deg is out of the engine's reach
    assert stiff["deform_reach_deg"] == pytest.approx(soft["deform_reach_deg"] / 2, rel=0.15)
    assert soft["shape_hover_fold_deg"] < 1 and not soft["shape_hover_blew_up"]


def test_the_shape_holding_thrust_leaves_the_rod_a_fraction_of_its_even_fold(cache_dir):
    """The rod's ends carry less mass per rotor than its middle: the even hover thrust curls them,
    the shape-holding one (statics.shape_hover_thrust) keeps them far flatter."""
    from sdexp.sim.drone import build_drone
    cfg = make_config("drone=rod")
    phys = fleet.physics_of(build_drone(cfg.drone, cache_dir, "quadratic"), cfg.sim, hold_seconds=1.0)
    assert phys["hover_fold_deg"] > 30 and phys["shape_hover_fold_deg"] < phys["hover_fold_deg"] / 3


@pytest.mark.parametrize("override, words", [
    ("experiment.params.tasks=[hover,loop]", ["experiment.params.tasks", "'loop'", "hover, reach, velocity, deform"]),
    ("experiment.params.controllers=[ours,neural]", ["experiment.params.controllers", "'neural'", "rigid_lqr"]),
    ("experiment.params.tasks=[]", ["experiment.params.tasks", "non-empty"]),
    ("experiment.params.seeds=[0,0]", ["experiment.params.seeds", "distinct"]),
    ("experiment.params.samples_per_channel=0", ["experiment.params.samples_per_channel", "> 0"]),
    ("experiment.params.drones=[rod,zeppelin]", ["drone 'zeppelin' is unknown", "flower"]),
])
def test_bad_fleet_lists_name_the_valid_choices_before_anything_runs(tmp_path, override, words):
    with pytest.raises(UserError) as err:
        run_experiment(make_cfg("experiment=fleet", override), tmp_path / "run")
    for w in words:
        assert w in str(err.value), str(err.value)
    assert not (tmp_path / "run").exists()


def test_a_drone_s_recipe_changes_its_learning_and_control_alone():
    rod = {"model": {"linear": ["d", "g", "h"], "command_delay": 0}, "control": {"delay_phase_deg": None},
           "data": {"samples": 60000}}
    cfg = make_config("experiment=fleet")
    p, none = replace(cfg.experiment.params, recipes={"rod": rod}), replace(cfg.experiment.params, recipes={})
    job, plain = fleet.job_config(cfg, "rod", 1, p), fleet.job_config(cfg, "rod", 1, none)
    assert job.model.linear == ["d", "g", "h"] and job.model.command_delay == 0 and job.control.delay_phase_deg is None
    assert job.data.samples == 60000 and plain.data.samples == 1500 * 11   # the recipe's samples win over the rule
    assert job.model.frame == plain.model.frame and job.control.r == plain.control.r   # the rest as the run's
    assert (job.drone, job.sim, job.noise, job.seed) == (plain.drone, plain.sim, plain.noise, plain.seed)
    assert job.data.workers == 1 and job.model.threads == 1   # one core a job, whatever the recipe
    assert fleet.job_config(cfg, "star", 1, p) == fleet.job_config(cfg, "star", 1, none)
    assert fleet.recipe_text(rod) == ("model.linear=[d, g, h] model.command_delay=0 control.delay_phase_deg=null "
                                      "data.samples=60000")


def test_a_job_resumes_only_from_a_result_made_with_its_config(tmp_path):
    cfg = make_config("experiment=fleet")
    p = cfg.experiment.params
    key = fleet.job_key(fleet.job_config(cfg, "rainbow", 0, p), p)
    def key_with(**changes):
        q = replace(p, **changes)
        return fleet.job_key(fleet.job_config(cfg, "rainbow", 0, q), q)
    # what this job flies: its own recipe, the tasks' params, the seed
    assert key_with(recipes={**p.recipes, "rainbow": {"control": {"r": 50.0}}}) != key
    assert key_with(speed=0.4) != key and fleet.job_key(fleet.job_config(cfg, "rainbow", 1, p), p) != key
    # ... not another drone's recipe, how many jobs run at once, or which other drones fly
    assert key_with(recipes={**p.recipes, "rod": {"data": {"samples": 100}}}) == key
    assert key_with(workers=1, drones=["rainbow"], seeds=[0]) == key
    path, recipe = tmp_path / "rainbow_seed0.json", fleet.recipe_text(p.recipes.get("rainbow"))
    for written, kept in (({"key": key}, True), ({"key": "fleet-job-other"}, False),
                          ({"recipe": recipe}, True), ({"recipe": "control.r=1"}, False)):   # unkeyed: the recipe
        path.write_text(json.dumps(written))
        assert (fleet.done_job(path, key, recipe) == written) is kept, written
    path.write_text('{"key": ')   # a damaged file is flown again
    assert fleet.done_job(path, key, recipe) is None and fleet.done_job(tmp_path / "none.json", key, recipe) is None


@pytest.mark.parametrize("recipe, words", [
    ("zeppelin={model:{linear:[d]}}", ["recipes.zeppelin", "not a drone", "flower"]),
    ("leaf={sim:{element:linear}}", ["recipes.leaf.sim", "only data, model, control"]),
    ("leaf={model:{linearr:[d]}}", ["recipes.leaf.model", "linearr"]),
    ("leaf.model=3", ["recipes.leaf.model = 3", "a mapping of model keys"]),
    ("leaf={model:{epochs:0}}", ["recipes.leaf", "model.epochs"]),
    # a recipe is checked with the run's other keys: the fleet's delay bound needs the delay it drops
    ("leaf={model:{command_delay:0}}", ["recipes.leaf", "control.delay_phase_deg", "model.command_delay is 0"]),
])
def test_a_bad_recipe_is_named_before_anything_runs(tmp_path, recipe, words):
    with pytest.raises(UserError) as err:   # a drone's recipe is added as Hydra adds a key: with +
        run_experiment(make_cfg("experiment=fleet", f"+experiment.params.recipes.{recipe}"), tmp_path / "run")
    for w in words:
        assert w in str(err.value), str(err.value)
    assert not (tmp_path / "run").exists()


def test_the_data_torque_map_fit_recovers_a_lagged_map_with_the_acting_command():
    """Angular accelerations driven by the command sent two steps earlier, in 0.1 s holds: the fit
    on the acting command finds the map, the one on the sent command a smaller one."""
    from sdexp.eval.fleet import data_torque_map
    rng = np.random.default_rng(0)
    n, dt, lag, hold = 6000, 0.01, 2, 10
    rigid = np.array([[1.0, -1.0, 0.5]])
    u = np.repeat(rng.uniform(-1, 1, (n // hold, 3)), hold, axis=0)
    episode = np.repeat(np.arange(n // 400), 400).astype(np.int32)
    acting = np.concatenate([u[:lag], u[:-lag]])
    e_dot = rng.normal(0, 0.01, (n, 1))
    arrays = {"u": u, "episode": episode, "e": rng.normal(0, 0.05, (n, 1)), "s": np.zeros((n, 0)),
              "e_dot": e_dot, "e_dot_next": e_dot + dt * (acting @ rigid.T + rng.normal(0, 0.5, (n, 1)))}
    fit = data_torque_map(arrays, rigid, [0], dt, lag)
    assert abs(fit["data_torque_map_ratio_acting"] - 1) < 0.05 and fit["data_torque_map_error_acting"] < 0.1
    assert fit["data_torque_map_ratio_sent"] < 0.9 and fit["data_level_transitions"] == n


def _row(survived=True, value=0.05, failure="", task="hover"):
    return {"task": task, "controller": "ours", "survived": survived, "survival_time": 1.2 if failure else 2.0,
            "failure": failure, "primary": "final_error", "primary_value": value, "tolerance": 0.1}


@pytest.mark.parametrize("row, kind, words", [
    (_row(value=0.059), "within", "within 0.1 m (0.059)"),
    (_row(value=2.74), "missed", "missed by 2.64 m (2.74 against 0.1)"),
    (_row(False, 3.0, "loss_of_control: tilt 93.1 deg > 90"), "lost control", "lost control at 1.20 s (tilt 93.1 deg)"),
    (_row(False, 3.0, "simulator: non-finite state"), "failed", "failed at 1.20 s (non-finite state)"),
    (_row(value=float("nan")), "missed", "missed: survived, its final_error not measured (tolerance 0.1 m)"),
    (_row(False, float("nan"), "beyond the body: its rotors bend it at most 1.7 deg", "deform"), "beyond the body",
     "beyond the body: its rotors bend it at most 1.7 deg"),
])
def test_every_flight_is_said_against_its_tolerance(row, kind, words):
    assert fleet.outcome(row) == kind and fleet.verdict(row) == words


def test_the_summary_counts_flights_within_missed_and_lost_per_task():
    """Three jobs of one drone, one of which did not fly: two hovers, one within and one missed."""
    metrics = {"jobs": 3, "jobs_failed": 1, "wall_seconds": 60.0, "rod_hover_ours_survived": 2, "rod_hover_ours_within": 1,
               "rod_reach_ours_survived": 1, "rod_reach_ours_within": 0}
    params = replace(FleetParams(), controllers=["ours"], tasks=["hover", "reach"])
    text = fleet.summary(params, metrics)
    assert "ours, of 2 flights a task against its tolerance: hover 1 within, 1 missed, 0 lost; " \
           "reach 0 within, 1 missed, 1 lost" in text
    table = fleet.fleet_table([{"drone": "rod", "seed": 0, "error": None, "samples": 800,
                                "rows": [{**_row(value=0.2), "drone": "rod", "seed": 0}]}])
    assert list(table["outcome"]) == ["missed"]


def test_a_jobs_phase_shows_in_the_fleets_progress_lines():
    """A job learns for minutes: the phase it is in shows beside the count of jobs done."""
    from sdexp.log import Phase
    with Phase("fleet jobs", total=2, unit="jobs", bar=False, heartbeat=False) as bar:
        report = fleet.job_progress(bar)
        report("rod seed 0: learning (data and nets)")
        assert bar.postfix == "now rod seed 0: learning (data and nets)"
        report(1)
        assert bar.n == 1
