"""The reduced-order model (sim.model = reduced, sdexp.sim.reduced): its mechanics against
conservation laws and against the full FEM it is built from, and what it refuses."""
import numpy as np
import pytest

from sdexp.config import DroneConfig
from sdexp.errors import UserError
from sdexp.sim.drone import assemble_drone
from sdexp.sim.mesh.shape import Shape
from sdexp.sim.mesh.structured import box_tets
from sdexp.sim.physics.fem import stable_substep
from sdexp.sim.physics.integrator import Body
from sdexp.sim.reduced.basis import deformations
from sdexp.sim.reduced.body import ReducedBody, frequencies, stable_substep as reduced_substep
from sdexp.sim.reduced.model import ReducedSpec, build_reduced
from sdexp.sim.reduced.snapshots import hover_thrust
from sdexp.sim.physics.modes import free_frequencies
from sdexp.sim.simulator import Simulator
from tests.sim.test_simulator import noise_cfg, sim_cfg

T = 0.12


def soft_plate(element: str = "quadratic", youngs: float = 2e4):
    """A 2.4 m x 0.12 m x 0.8 m plate, 3 rotors, 2 IMUs: soft enough to bend in flight."""
    pts, tets = box_tets((12, 1, 4), (2.4, T, 0.8), (-1.2, -T / 2, -0.4))
    up = np.array([0.0, 1.0, 0.0])
    shape = Shape(3, np.zeros((0, 3)), np.zeros((0, 3), int), np.zeros((0, 3)), np.zeros(3),
                  rotors=np.array([[-1.0, T / 2, 0], [0, T / 2, 0.2], [1.0, T / 2, 0]]),
                  rotor_normals=np.tile(up, (3, 1)), imus=np.array([[-0.9, T / 2, 0.0], [0.9, T / 2, 0.0]]),
                  imu_normals=np.tile(up, (2, 1)), frame_imus=np.array([[0.0, T / 2, 0.0]]), frame_normals=up[None])
    cfg = DroneConfig(name="plate", shape="test", size=[2.4, T, 0.8], youngs_modulus=youngs, num_rotors=3,
                      num_sensors=2, rotor_radius=0.25, imu_radius=0.25)
    return assemble_drone(cfg, shape, pts, tets, element)


SPEC = ReducedSpec(basis=24, linear_modes=8, cubature=60, snapshot_seconds=6.0, modal_derivatives=3)  # sim.reduced below too


@pytest.fixture(scope="module")
def plate_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("reduced"))


@pytest.fixture(scope="module")
def plate(plate_cache):
    drone = soft_plate()
    return drone, build_reduced(drone, SPEC, plate_cache)


def angular_momentum(x, v, mass):
    c = mass @ x / mass.sum()
    return np.sum(mass[:, None] * np.cross(x - c, v), axis=0)


def _spin(model, dt: float, seconds: float):
    """A deformed, vibrating body spun up and left alone (no damping, gravity or thrust):
    (its momenta before, after), read from the rebuilt mesh."""
    body = ReducedBody(model)
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, 0.3, model.r) * (model.z_hi - model.z_lo) / 4
    body.place(model.com, np.eye(3), z, v=[0.3, -0.1, 0.2], w=[0.4, 2.0, -0.7], zd=rng.normal(0.0, 0.5, model.r))
    mass = model.drone.fem.mass
    before = angular_momentum(body.x, body.v, mass), mass @ body.v
    for _ in range(int(round(seconds / dt))):
        body.run(1, dt)
    assert np.linalg.norm(body.w) > 0.5 and np.abs(body.zd).max() > 0      # it still spins and rings
    return before, (angular_momentum(body.x, body.v, mass), mass @ body.v)


def test_a_free_spinning_deformed_body_keeps_its_momenta(plate):
    """Linear momentum exactly; angular momentum to the integrator's first order: symplectic Euler
    in a rotating frame drifts by O(dt), so a quarter of the step leaves a quarter of the drift.
    A wrong coupling term (the inertia's polynomials in z, the Coriolis or centrifugal terms) would
    leave a drift that no step removes."""
    _, model = plate
    dt = 0.5 * reduced_substep(model, 0.8)
    drift = []
    for step in (dt, dt / 4):
        (L0, p0), (L1, p1) = _spin(model, step, 0.3)
        np.testing.assert_allclose(p1, p0, atol=1e-10)
        drift.append(np.linalg.norm(L1 - L0) / np.linalg.norm(L0))
    assert drift[1] < 0.35 * drift[0]
    assert drift[1] < 3e-3


def test_the_reduced_model_follows_the_full_one(plate):
    """The same thrust holds around hover on both models for 1.5 s, noise off: the centre of mass
    stays within centimetres and the deformation (rigid motion removed) within 15% of the full
    model's, at a fraction of the substeps; the first free-free frequencies within 3%."""
    drone, model = plate
    fem = drone.fem
    full = Body(fem, 1, drone.rotors)
    red = ReducedBody(model)
    n_full = int(np.ceil(0.01 / stable_substep(fem, 0.8)))
    n_red = int(np.ceil(0.01 / reduced_substep(model, 0.8)))
    assert n_red < n_full / 2
    rng = np.random.default_rng(5)
    hover = hover_thrust(drone, 9.81)
    num = den = 0.0
    for k in range(150):
        if k % 10 == 0:
            u = hover + rng.uniform(-0.3, 0.3, 3) * drone.max_thrust * 0.2
        full.run(n_full, 0.01 / n_full, u, drone.damping, 9.81, drone.deformation_damping)
        red.run(n_red, 0.01 / n_red, u, drone.damping, 9.81, drone.deformation_damping)
        if k % 5 == 4:
            uf, ur = deformations(np.array([full.x, red.x]), model.X, fem.mass)
            num += np.sum(fem.mass[:, None] * (uf - ur) ** 2)
            den += np.sum(fem.mass[:, None] * uf ** 2)
    assert np.sqrt(num / den) < 0.15
    assert np.linalg.norm(fem.mass @ (full.x - red.x)) / fem.mass.sum() < 0.03
    np.testing.assert_allclose(frequencies(model, 4), free_frequencies(fem, k=4), rtol=0.03)


def test_the_linear_modes_stiffness_is_exact(plate, plate_cache):
    """sim.reduced.exact_modes (the default) makes the rest stiffness among the linear modes the
    full model's: the first free-free frequencies within 0.1%, where the cubature alone (the
    same cached build, loaded without it) is further off; and the step feels it (the frequencies
    come from finite differences of the step's own force)."""
    from dataclasses import replace
    drone, model = plate
    full = free_frequencies(drone.fem, k=6)
    assert model.stiffness_fix.shape == (SPEC.linear_modes, SPEC.linear_modes)
    exact = np.abs(frequencies(model, 6) / full - 1).max()
    bare = build_reduced(drone, replace(SPEC, exact_modes=False), plate_cache)   # the same entry, loaded
    assert bare.stiffness_fix.shape == (0, 0)
    cubature = np.abs(frequencies(bare, 6) / full - 1).max()
    assert exact < 1e-3 < cubature


def test_a_flight_that_leaves_the_fitted_range_ends_as_a_recorded_failure(plate, monkeypatch, tmp_path):
    drone, model = plate
    monkeypatch.setenv("SDEXP_CACHE", str(tmp_path))
    sim = Simulator(drone, sim_cfg(model="reduced", reduced=dict(basis=24, linear_modes=8, cubature=60,
                                                                 snapshot_seconds=6.0, modal_derivatives=3)), noise_cfg(enabled=False))
    lo, hi = sim.reduced.z_lo, sim.reduced.z_hi
    sim.body.z[0] = hi[0] + 0.05 * (hi[0] - lo[0])   # just past the fitted range, no further
    sim.step(np.zeros(3))
    assert sim.failure is not None and sim.failure.reason == "left_reduced_range"
    assert "modal coordinate" in sim.failure.detail


@pytest.mark.parametrize("override, key", [(dict(ground=0.0), "sim.ground"), (dict(mass_scaling=0.01), "sim.mass_scaling"),
                                           (dict(effects=[{"name": "payload", "mass": 0.1}]), "Payload")])
def test_what_the_reduced_model_cannot_carry_is_refused_by_name(plate, override, key):
    drone, _ = plate
    with pytest.raises(UserError, match=key):
        Simulator(drone, sim_cfg(model="reduced", **override), noise_cfg(enabled=False))


def test_the_plain_spec_has_the_configs_defaults():
    from dataclasses import fields
    from sdexp.config import ReducedConfig
    from sdexp.sim.reduced.model import spec_of
    assert spec_of(ReducedConfig()) == ReducedSpec()
    assert {f.name for f in fields(ReducedConfig)} <= {f.name for f in fields(ReducedSpec)}
