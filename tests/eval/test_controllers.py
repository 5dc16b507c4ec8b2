"""The controller registry (sdexp.eval.controllers.CONTROLLERS): the paper's four by name (and the
privileged reduced-model LQR, tests/control/test_modal_lqr.py), each
built as a Controller labelled with its key. The rigid baselines are built here from a simulator
alone; ours and the neural policy need a learned model, and the shrunk sota run flies all four
(tests/eval/test_control_experiments.py)."""
import pytest

from sdexp.control.controller import Controller
from sdexp.eval.controllers import CONTROLLERS, build
from sdexp.sim.drone import build_drone
from sdexp.sim.simulator import Simulator
from tests.conftest import make_config


def test_the_registry_holds_the_papers_four_in_their_order_then_the_privileged_baseline():
    assert list(CONTROLLERS) == ["ours", "rigid_lqr", "geometry_lqr", "neural", "reduced_lqr"]


def test_a_registered_controller_is_a_controller_under_its_name(cache_dir):
    cfg = make_config("drone=rod", f"cache_dir={cache_dir}")
    drone = build_drone(cfg.drone, cache_dir, cfg.sim.element)
    for name in ("rigid_lqr", "geometry_lqr"):
        ctl = build(name, cfg, Simulator(drone, cfg.sim, cfg.noise, seed=0))
        assert isinstance(ctl, Controller) and ctl.name == name


def test_an_unknown_controller_names_the_registered_ones():
    with pytest.raises(ValueError, match="'nope': choose from ours, rigid_lqr, geometry_lqr, neural, reduced_lqr"):
        build("nope", None, None)
