"""A shrunk setting of the workflow shared by its tests: the bench drone (coarse, damped leaf),
short flights, few windows and a handful of candidates."""
import pytest

from sdexp.sim.drone import build_drone
from tests.conftest import make_config

SMALL = [
    "drone=leaf", "drone.mesh.edge_length=0.5",   # the bench drone
    "sim.element=linear",                          # as the bench (conf/experiment/discrepancy_bench.yaml)
    "discrepancy.horizon=0.15", "discrepancy.stride=0.4", "discrepancy.history=0.2",
    "discrepancy.fit_windows=16", "discrepancy.screen=2", "discrepancy.floor_flights=3",
    "discrepancy.max_effects=1", "discrepancy.candidates=[payload,thrust_loss,quadratic_drag,motor_lag]",
    "discrepancy.record.flights=4", "discrepancy.record.seconds=3.0",
    "discrepancy.push=false",                      # its own test turns it on
]


@pytest.fixture(scope="session")
def small_cfg(cache_dir):
    return make_config(*SMALL, "experiment=discrepancy", f"cache_dir={cache_dir}")


@pytest.fixture(scope="session")
def leaf(small_cfg):
    return build_drone(small_cfg.drone, small_cfg.cache_dir, small_cfg.sim.element)
