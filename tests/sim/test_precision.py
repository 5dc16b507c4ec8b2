"""sim.precision (float32 elastic forces, float64 state) and sim.mass_scaling (targeted inertia):
the float32 kernels agree with each other and with float64 to float32's rounding, a float32
flight stays on the float64 one, the added inertia lowers the largest eigenvalue where it is
meant to and leaves gravity on the physical mass; both keys enter cache keys only when set."""
import logging

import numpy as np
import pytest

from sdexp import conf
from sdexp.cache import config_key
from sdexp.config import NoiseConfig, SimConfig
from sdexp.sim.drone import build_drone
from sdexp.sim.mesh.structured import box_tets, box_tris
from sdexp.sim.physics.fem import build_fem, elastic_forces, stable_substep
from sdexp.sim.physics.integrator import Body
from sdexp.sim.physics.modes import free_frequencies, mass_scaling, stiffness, targeted_mass, top_modes
from sdexp.sim.physics.quadratic import quadratic_mesh
from sdexp.sim.physics.reference import corotated_forces_3d_f32
from sdexp.sim.simulator import Simulator


def _block(dim, order):
    pts, el = box_tets((4, 2, 3), (1.0, 0.4, 0.6), (-0.5, -0.2, -0.3)) if dim == 3 else box_tris((8, 3), (1.0, 0.4), (-0.5, -0.2))
    if order == 2:
        pts, el = quadratic_mesh(pts, el)
    return build_fem(pts, el, 1.0, 5000.0, 0.3)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("dim", [2, 3])
def test_float32_kernels_agree(dim, order):
    """One force evaluation of a stretched, jittered block 3 m from the origin: the compiled
    float32 kernel against its numba twin to float32's rounding (5e-7 of the largest force
    measured), and both within 2e-6 of float64."""
    fem = _block(dim, order)
    x = 1.02 * fem.rest + 0.01 * np.random.default_rng(1).standard_normal(fem.rest.shape) + 3.0
    forces = {}
    for precision, real in (("float64", np.float64), ("float32", np.float32)):
        body = Body(fem, precision=precision)
        body.x[:] = x
        body.forces_only(1)
        forces[precision] = body.fbuf[0].copy()
        twin = corotated_forces_3d_f32.ctypes if (dim, order, real) == (3, 1, np.float32) else None
        forces[precision + " numba"] = elastic_forces(fem, x, kernel=twin, real=real)
    scale = np.abs(forces["float64 numba"]).max()
    assert np.abs(forces["float64"] - forces["float64 numba"]).max() < 1e-13 * scale
    assert np.abs(forces["float32"] - forces["float32 numba"]).max() < 2e-6 * scale
    assert 0 < np.abs(forces["float32"] - forces["float64"]).max() < 2e-6 * scale


@pytest.fixture(scope="module")
def rod(cache_dir):
    return build_drone(conf.drone("rod"), cache_dir, "quadratic")


def test_float32_flight_stays_on_the_float64_one(rod):
    """A noise-free rod flight of 0.5 s under random thrust holds (it tumbles and bends):
    float32 forces keep every vertex within 1e-5 m and the IMU bends within 1e-3 deg of
    float64 (the rod bends by tens of degrees)."""
    noise = NoiseConfig(enabled=False)
    sims = [Simulator(rod, SimConfig(precision=p, threads=1), noise, 0) for p in ("float64", "float32")]
    rng = np.random.default_rng(0)
    bend = 0.0
    for k in range(50):
        if k % 10 == 0:
            hold = rng.uniform(-1, 1, rod.num_rotors) * rod.max_thrust
        for sim in sims:
            sim.step(hold)
        assert all(s.alive for s in sims)
        s64, s32 = (s.state(noisy=False).s for s in sims)
        assert np.abs(s64 - s32).max() < np.deg2rad(1e-3)
        bend = max(bend, np.abs(s64).max())
    assert np.abs(sims[0].x - sims[1].x).max() < 1e-5
    assert np.rad2deg(bend) > 5, "the flight should bend the rod"


def test_targeted_inertia_buys_the_step_where_the_modes_live():
    """A quadratic block with one node pushed 0.14 m toward its top face (thin elements under
    it, the kind of spot that limits a drone's step): a 0.5% budget lowers lambda_max(M^-1 K)
    by the gain it reports (x1.3), within the budget, while the first free-free frequencies
    move far less than uniform scaling for the same step gain would move them (-1 / gain)."""
    pts, el = box_tets((4, 2, 3), (1.0, 0.4, 0.6), (-0.5, -0.2, -0.3))
    pts[np.argmin(np.linalg.norm(pts - [0.0, 0.0, 0.1], axis=1)), 1] += 0.14
    fem = build_fem(*quadratic_mesh(pts, el), 1.0, 5000.0, 0.3)
    added, gain = targeted_mass(fem, 0.005)
    assert gain >= 1.25 and 0 < added.sum() <= 0.005 * fem.mass.sum()
    K = stiffness(fem)
    lam0, lam1 = top_modes(K, fem.mass, 3)[0][0], top_modes(K, fem.mass + added, 3)[0][0]
    assert np.sqrt(lam0 / lam1) == pytest.approx(gain, rel=2e-3)
    df = free_frequencies(fem, fem.mass + added, K=K, k=4) / free_frequencies(fem, K=K, k=4) - 1
    assert np.all(df <= 0) and np.abs(df).max() < 0.2 * (1 - 1 / gain)
    # the power iteration that sets the simulator's step sees the same gain
    assert stable_substep(fem, 1.0, mass=fem.mass + added) / stable_substep(fem, 1.0) == pytest.approx(gain, rel=0.02)


def test_gravity_pulls_on_the_physical_mass():
    """A free block with inertia added to some nodes, under gravity alone: its momentum grows
    by the physical weight, so its centre of (inertial) mass falls at g M / M'."""
    fem = _block(3, 2)
    added = np.where(np.arange(len(fem.rest)) % 5 == 0, fem.mass, 0.0)
    body = Body(fem, added_mass=added)
    dt, n = 2e-4, 500
    body.run(n, dt, gravity=9.81)
    momentum = np.sum(body.mass[:, None] * body.v, axis=0)
    assert momentum[1] == pytest.approx(-9.81 * fem.mass.sum() * n * dt, rel=1e-9)
    assert abs(momentum[0]) + abs(momentum[2]) < 1e-12


def test_a_budget_that_buys_nothing_runs_unscaled(rod, caplog, tmp_path):
    """A budget below the first rung's needs: a warning that says so, the unscaled step."""
    assert mass_scaling(rod.fem, 1e-9, tmp_path).added is None
    plain = Simulator(rod, SimConfig(threads=1), NoiseConfig(enabled=False), 0)
    with caplog.at_level(logging.WARNING):
        tiny = Simulator(rod, SimConfig(threads=1, mass_scaling=1e-9), NoiseConfig(enabled=False), 0)
    assert tiny.scaling.added is None and tiny.n_sub == plain.n_sub
    assert "no step gain" in caplog.text and "running unscaled" in caplog.text


def test_new_sim_keys_enter_cache_keys_only_when_set():
    """Every artefact cached before sim.precision and sim.mass_scaling existed keeps its key at
    their defaults; set, they enter it."""
    plain = config_key(SimConfig())
    assert "precision" not in plain and "mass_scaling" not in plain
    assert config_key(SimConfig(precision="float32"))["precision"] == "float32"
    assert config_key(SimConfig(mass_scaling=0.005))["mass_scaling"] == 0.005
