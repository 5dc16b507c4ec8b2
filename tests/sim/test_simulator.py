"""The simulator's actuation, noise, delay, contact and failure handling."""
import numpy as np
import pytest
from omegaconf import OmegaConf

from sdexp.config import NoiseConfig, SimConfig
from sdexp.sim.simulator import Simulator
from tests.sim.test_sensors import beam_drone_2d, plate_drone


def sim_cfg(**kw):
    """A SimConfig, the values typed as the schema types them (a YAML's 0 is 0.0)."""
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(SimConfig), kw))


def noise_cfg(**kw):
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(NoiseConfig), kw))


QUIET = dict(enabled=False)


@pytest.fixture(scope="module")
def plate():
    return plate_drone()


def test_free_fall_without_thrust(plate):
    # float64 unscaled, to hold the integrator to 1e-9: inertia added without weight
    # (sim.mass_scaling) falls slower by its share (tests/sim/test_precision.py holds the scaled
    # body's momentum to gravity on the physical mass), float32 forces stir it by 6e-9
    sim = Simulator(plate, sim_cfg(mass_scaling=0.0, precision="float64"), noise_cfg(**QUIET))
    p0 = sim.state().p
    plate.damping, damping = 0.0, plate.damping
    try:
        for _ in range(20):
            sim.step(np.zeros(3))
    finally:
        plate.damping = damping
    st = sim.state()
    # symplectic Euler's exact discrete free fall: -g/2 T (T + dt)
    assert st.p[1] - p0[1] == pytest.approx(-0.5 * 9.81 * 0.2 * (0.2 + sim.dt), rel=1e-9)
    assert st.p_dot[1] == pytest.approx(-9.81 * 0.2, rel=1e-3)


def test_thrust_pushes_along_the_surface_normal_with_the_commanded_magnitude(plate):
    sim = Simulator(plate, sim_cfg(gravity=0.0), noise_cfg(**QUIET))
    u = np.array([1.0, 2.0, 1.0])
    sim.step(u)
    # momentum gained in one control step equals the thrust impulse (mass damping aside)
    m = plate.fem.mass[:, None]
    P = (m * sim.v).sum(0)
    np.testing.assert_allclose(sim.thrust_directions, np.tile([0, 1.0, 0], (3, 1)), atol=1e-2)
    assert P[1] == pytest.approx(u.sum() * 0.01, rel=0.02)
    assert abs(P[0]) < 1e-4 and abs(P[2]) < 1e-4


def test_commands_are_clipped_delayed_and_perturbed(plate):
    n = noise_cfg(angle_std_deg=0, position_std=0, angle_rate_std_deg=0, velocity_std=0, rotor_std=0.0)
    sim = Simulator(plate, sim_cfg(), n)
    applied = []
    for k in range(6):
        sim.step(np.full(3, 100.0 if k == 0 else 0.0))
        applied.append(sim.applied.copy())
    assert [a[0] for a in applied] == [0.0, 0.0, 0.0, 10.0, 0.0, 0.0]  # 30 ms, clipped to 10 N
    sim = Simulator(plate, sim_cfg(), noise_cfg(delay=0.0))
    draws = []
    for _ in range(200):
        sim.step(np.full(3, 5.0))
        draws.append(sim.applied - 5.0)
    assert np.std(draws) == pytest.approx(0.1, rel=0.15)


def test_sensor_noise_has_the_configured_levels(plate):
    sim = Simulator(plate, sim_cfg(), noise_cfg(), seed=3)
    clean = sim.readings(noisy=False)
    pos = np.array([sim.readings().pos - clean.pos for _ in range(300)])
    e = np.array([sim.state().e for _ in range(300)])
    assert pos.std() == pytest.approx(0.01, rel=0.1)
    assert np.rad2deg(e.std(axis=0)) == pytest.approx([0.573] * 3, rel=0.15)


def test_same_seed_same_episode(plate):
    runs = []
    for _ in range(2):
        sim = Simulator(plate, sim_cfg(), noise_cfg(), seed=7)
        runs.append([sim.step(np.full(3, 4.0)).pos for _ in range(5)])
    np.testing.assert_array_equal(runs[0], runs[1])


def test_blow_up_ends_the_episode_as_a_recorded_failure(plate):
    sim = Simulator(plate, sim_cfg(substep=0.01), noise_cfg(**QUIET))  # 10x the stable step
    for _ in range(50):
        sim.step(np.array([10.0, -10.0, 10.0]))
        if not sim.alive:
            break
    assert not sim.alive
    assert sim.failure.reason in {"inverted_element", "non_finite", "runaway_speed", "runaway_extent"}
    assert 0 < sim.failure.time <= 0.5
    frozen = sim.step(np.zeros(3))  # stepping a failed episode is harmless
    assert np.all(np.isfinite(frozen.pos))


def test_each_failure_check_names_its_reason(plate):
    sim = Simulator(plate, sim_cfg(), noise_cfg(**QUIET))
    sim.body.v[3, 1] = np.nan
    sim.step(np.zeros(3))
    assert sim.failure.reason == "non_finite"
    # a body stretched past max_stretch x its rest size: a 10% stretch against a 5% limit
    sim = Simulator(plate, sim_cfg(max_stretch=1.05), noise_cfg(**QUIET))
    sim.body.x[:] = plate.fem.rest * np.array([1.1, 1.0, 1.0])
    sim.step(np.zeros(3))
    assert sim.failure.reason == "runaway_extent"
    sim = Simulator(plate, sim_cfg(max_speed=1.0), noise_cfg(**QUIET))
    sim.body.v[:] = [2.0, 0.0, 0.0]
    sim.step(np.zeros(3))
    assert sim.failure.reason == "runaway_speed"


def test_ground_stops_a_falling_drone_and_boxes_keep_vertices_out():
    beam = beam_drone_2d()
    sim = Simulator(beam, sim_cfg(ground=-0.5, obstacles=[{"min": [-0.3, -2.0], "max": [0.3, -0.2]}]),
                    noise_cfg(**QUIET))
    for _ in range(150):
        sim.step(np.zeros(2))
    assert sim.alive
    assert sim.x[:, 1].min() >= -0.5 - 1e-9
    inside = (np.abs(sim.x[:, 0]) < 0.3 - 1e-9) & (sim.x[:, 1] < -0.2 - 1e-9)
    assert not inside.any()
    assert np.abs(sim.v).max() < 0.5  # come to rest (draped over the box)


def test_a_mesh_without_a_stable_substep_is_a_user_error_naming_the_mesh(plate, monkeypatch):
    from sdexp.errors import UserError
    import sdexp.sim.simulator as simulator
    monkeypatch.setattr(simulator, "stable_substep", lambda fem, safety, mass=None: float("nan"))
    with pytest.raises(UserError, match=r"drone plate: no stable explicit substep.*drone\.mesh"):
        Simulator(plate, sim_cfg(), noise_cfg())
