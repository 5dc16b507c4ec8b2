"""The privileged reduced-model LQR (``reduced_lqr``, sdexp.control.modal_lqr): it flies a soft
plate on its own reduced model and on the full FEM it observes through the best-fit frame, and
a flight of a controller without a learned model trains nothing."""
from dataclasses import replace

import numpy as np
import pytest

from sdexp.control.rollout import fly
from sdexp.control.tasks import Task
from sdexp.eval.controllers import build
from sdexp.sim.simulator import Simulator
from tests.conftest import make_config
from tests.sim.test_reduced import soft_plate

REDUCED = ["sim.reduced.basis=24", "sim.reduced.linear_modes=8", "sim.reduced.cubature=60",
           "sim.reduced.snapshot_seconds=6.0", "sim.reduced.modal_derivatives=3"]


@pytest.fixture(scope="module")
def plate_and_cfg(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    mp = pytest.MonkeyPatch()
    mp.setenv("SDEXP_CACHE", str(cache))
    cfg = make_config("noise.enabled=false", f"cache_dir={cache}", *REDUCED)
    yield soft_plate(youngs=2e5), cfg   # stiffer than the reduced tests' plate: the least thrust that
    # holds its three rotors' torques carries the weight on the tips alone, which folds the softer one
    mp.undo()


@pytest.mark.parametrize("model", ["reduced", "full"])
def test_it_flies_the_plate_to_a_goal_on_either_model(plate_and_cfg, model):
    """From rest toward a goal 0.6 m away for 3 s (ours' waypoint, kp of the way every n steps):
    no failure, and the distance to the goal more than halved, on the reduced model and on the
    full FEM it observes through the best-fit frame."""
    plate, cfg = plate_and_cfg
    cfg = replace(cfg, sim=replace(cfg.sim, model=model))
    sim = Simulator(plate, cfg.sim, cfg.noise)
    ctl = build("reduced_lqr", cfg, sim)
    task = Task(start=np.zeros(3), target=np.array([0.3, 0.4, 0.3]), seconds=3.0, n_s=plate.layout.n_s)
    flight = fly(sim, ctl, task, limits=cfg.flight)
    assert flight.failure is None
    p = sim.state(noisy=False).p   # the measured point, released at task.start
    assert np.linalg.norm(p - task.target) < 0.5 * np.linalg.norm(task.target - task.start)


def test_a_flight_without_a_learned_model_trains_nothing(plate_and_cfg, monkeypatch):
    """Setup identifies (data, d, g, h) only when a controller flies on the learned model."""
    from sdexp.eval import flights
    import sdexp.model.identification as identification
    plate, cfg = plate_and_cfg
    monkeypatch.setattr(identification, "identify", lambda *a, **k: pytest.fail("identified"))
    monkeypatch.setattr("sdexp.sim.drone.build_drone", lambda *a, **k: plate)
    setup = flights.Setup(cfg, progress=False)
    sim = setup.simulator()
    task = setup.task(np.zeros(3), np.array([0.0, 0.2, 0.0]), 0.5)
    _, m = setup.fly(sim, setup.controller("rigid_lqr", sim), task)
    assert np.isfinite(m["final_error"])
    assert setup.layout.slices["p"] == slice(2 * plate.layout.n_s + 6, 2 * plate.layout.n_s + 9)
