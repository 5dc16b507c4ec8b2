"""Each library effect against the physics it models, zero strength = nominal bitwise, and
the plugin protocol."""
from dataclasses import replace

import numpy as np
import pytest

from sdexp.errors import UserError
from sdexp.sim.physics.effects import Effect, LIBRARY, build_effects, vertex_areas
from sdexp.sensing.rotations import quat_from_matrix  # noqa: F401  (set_state uses it)
from sdexp.sim.simulator import Simulator
from tests.sim.test_sensors import beam_drone_2d, plate_drone
from tests.sim.test_simulator import QUIET, noise_cfg, sim_cfg


@pytest.fixture(scope="module")
def plate():
    return plate_drone()


@pytest.fixture(scope="module")
def beam():
    return beam_drone_2d()


@pytest.fixture(scope="module")
def undamped(plate):
    """The plate without mass-proportional damping, so forces read as accelerations."""
    return replace(plate, damping=0.0)


def com(sim, a):
    """Mass-weighted mean of a per-vertex array: the centre of mass's position or velocity
    (the IMU mean p also moves as the plate bends)."""
    m = sim.fem.mass
    return m @ a / m.sum()


def test_each_library_effect_declares_its_docs_bench_strengths_and_zero():
    """What the bench and the bitwise test below read from the class: a new effect is one class."""
    import inspect
    for cls in LIBRARY.values():
        assert cls.description and cls.equation, cls.name
        key, moderate, strong = cls.bench_strengths
        arguments = inspect.signature(cls).parameters
        assert key in arguments and moderate != strong, cls.name
        assert set(cls.zero(3)) <= set(arguments), cls.name


@pytest.mark.parametrize("drone", ["plate", "beam"])
def test_zero_strength_effects_are_nominal_bitwise(drone, request):
    """Every library effect at its declared zero (the 3D plate, the 2D beam) at once."""
    body = request.getfixturevalue(drone)
    zero = [{"name": name, **cls.zero(body.dim)} for name, cls in LIBRARY.items() if cls.zero(body.dim) is not None]
    assert len(zero) == len(LIBRARY) - (body.dim == 2)   # rotor_reaction_torque is 3D only
    u = np.array([4.0, 3.0, 4.5])[:body.num_rotors]
    runs = []
    for effects in ([], zero):
        sim = Simulator(body, sim_cfg(effects=effects), noise_cfg(), seed=3)
        for k in range(15):
            r = sim.step(u + 0.5 * np.sin(k))
        runs.append((sim.x.copy(), sim.v.copy(), r.pos.copy(), r.rot.copy()))
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


def test_motor_lag_step_response_has_the_time_constant(plate):
    tau = 0.08
    sim = Simulator(plate, sim_cfg(gravity=0.0, effects=[{"name": "motor_lag", "tau": tau}]), noise_cfg(**QUIET))
    lag = sim.effects[0]
    states = []
    for _ in range(30):
        sim.step(np.full(3, 2.0))
        states.append(lag.state[0])
    t = 0.01 * np.arange(1, 31)
    assert np.allclose(states, 2.0 * (1 - np.exp(-t / tau)), rtol=1e-12)
    # the applied thrust is the interval mean, so its integral is the exact response's
    applied_integral = 0.0
    sim.reset()
    for _ in range(30):
        sim.step(np.full(3, 2.0))
        applied_integral += 0.01 * sim.applied[0]
    T = 0.3
    assert applied_integral == pytest.approx(2.0 * (T - tau * (1 - np.exp(-T / tau))), rel=1e-9)


def test_actuation_delay_shifts_the_command_by_a_fractional_delay(plate):
    sim = Simulator(plate, sim_cfg(gravity=0.0, effects=[{"name": "actuation_delay", "delay": 0.025}]),
                    noise_cfg(**QUIET))
    cmds = np.arange(1, 11, dtype=float)
    applied = []
    for c in cmds:
        sim.step(np.full(3, c))
        applied.append(sim.applied[0])
    # u(t - 2.5 steps): the mean of the commands 2 and 3 steps back (zeros before the start)
    past = np.r_[0.0, 0.0, 0.0, cmds]
    assert np.allclose(applied, 0.5 * (past[1:11] + past[0:10]))


def test_thrust_loss_weakens_one_rotor(plate):
    sim = Simulator(plate, sim_cfg(effects=[{"name": "thrust_loss", "rotor": 2, "fraction": 0.3}]), noise_cfg(**QUIET))
    sim.step(np.full(3, 5.0))
    assert np.allclose(sim.applied, [5.0, 5.0, 3.5])


def test_ground_effect_gain_is_cheeseman_bennett(plate):
    R = 0.8
    sim = Simulator(plate, sim_cfg(gravity=0.0, effects=[{"name": "ground_effect", "radius": R, "ground": -0.6}]),
                    noise_cfg(**QUIET))
    sim.step(np.full(3, 3.0))
    h = 0.05 + 0.6  # rotor patches sit on the top surface, y = +0.05
    assert np.allclose(sim.applied, 3.0 / (1 - (R / (4 * h)) ** 2), rtol=1e-3)
    far = Simulator(plate, sim_cfg(gravity=0.0, effects=[{"name": "ground_effect", "radius": R, "ground": -50.0}]),
                    noise_cfg(**QUIET))
    far.step(np.full(3, 3.0))
    assert np.allclose(far.applied, 3.0, rtol=1e-4)


def test_payload_shifts_the_hover_thrust_by_its_weight(undamped):
    m = 0.2
    g = 9.81
    thrust = np.full(3, (1.0 + m) * g / 3)  # hover thrust of drone plus payload
    sims = {}
    for name, effects in (("nominal", []), ("payload", [{"name": "payload", "mass": m}])):
        sim = Simulator(undamped, sim_cfg(effects=effects), noise_cfg(**QUIET))
        y0 = com(sim, sim.x)[1]
        for _ in range(20):
            sim.step(thrust)
        sims[name] = com(sim, sim.x)[1] - y0
    t = 0.2
    # both lose the same little thrust to the rotor patches tilting as the plate bends: the
    # difference is the payload's weight, m g / M of acceleration
    assert abs(sims["payload"]) < 0.05 * sims["nominal"]
    assert sims["nominal"] - sims["payload"] == pytest.approx(0.5 * m * g / 1.0 * t * t, rel=0.01)


def test_quadratic_drag_reaches_the_terminal_velocity(beam):
    c = 2.0
    beam.damping, damping = 0.0, beam.damping
    try:
        sim = Simulator(beam, sim_cfg(effects=[{"name": "quadratic_drag", "c": c}]), noise_cfg(**QUIET))
        for _ in range(150):
            sim.step(np.zeros(2))
        area = vertex_areas(beam.fem.rest, beam.boundary).sum()
        v_term = np.sqrt(beam.fem.mass.sum() * 9.81 / (c * area))
        assert -sim.state().p_dot[1] == pytest.approx(v_term, rel=0.03)
    finally:
        beam.damping = damping


def test_wind_pushes_a_resting_body_with_c_A_w_abs_w(beam):
    c, w = 0.5, 2.0
    beam.damping, damping = 0.0, beam.damping
    try:
        sim = Simulator(beam, sim_cfg(gravity=0.0, effects=[{"name": "wind", "velocity": [w, 0.0], "c": c}]),
                        noise_cfg(**QUIET))
        sim.step(np.zeros(2))
        a = com(sim, sim.v)[0] / 0.01
        area = vertex_areas(beam.fem.rest, beam.boundary).sum()
        assert a == pytest.approx(c * area * w * w / beam.fem.mass.sum(), rel=1e-9)
    finally:
        beam.damping = damping


def test_rotor_drag_damps_in_plane_velocity_exponentially(undamped):
    k = 0.2
    sim = Simulator(undamped, sim_cfg(gravity=0.0, effects=[{"name": "rotor_drag", "k": k}]), noise_cfg(**QUIET))
    v0 = 1.0
    sim.body.v[:, 0] = v0
    sim.body.v[:, 1] = 0.5   # along the rotor axes: no drag
    for _ in range(50):
        sim.step(np.zeros(3))
    v = com(sim, sim.v)
    # three rotors, each -k v: dv/dt = -3 k v / M
    assert v[0] == pytest.approx(v0 * np.exp(-3 * k * 0.5 / 1.0), rel=0.01)
    assert v[1] == pytest.approx(0.5, rel=0.01)


@pytest.mark.parametrize("mount", [None, 0.3])
def test_reaction_torque_gives_the_predicted_yaw_acceleration(undamped, mount):
    """Whole-body (default) or mount-disc couple: the body's angular momentum about the centre
    of mass grows at the predicted torque, I alpha = -3 k T about +Y, with no net force."""
    k, T = 0.05, 2.0
    sim = Simulator(undamped, sim_cfg(gravity=0.0, effects=[
        {"name": "rotor_reaction_torque", "k": k, "spin": [1.0, 1.0, 1.0], "mount_radius": mount}]),
        noise_cfg(**QUIET))
    steps = 10
    for _ in range(steps):
        sim.step(np.full(3, T))
    m = sim.fem.mass
    L = np.sum(m[:, None] * np.cross(sim.x - com(sim, sim.x), sim.v), axis=0)
    t = steps * 0.01
    assert L[1] == pytest.approx(-3 * k * T * t, rel=0.03)
    assert np.allclose(L[[0, 2]], 0.0, atol=0.01 * abs(L[1]))
    # a pure torque: no net horizontal force (the thrust along the tilting normals adds ~1e-4)
    assert np.allclose(com(sim, sim.v)[[0, 2]], 0.0, atol=1e-3)


def test_reaction_torque_is_refused_in_2d(beam):
    with pytest.raises(UserError, match="3D"):
        Simulator(beam, sim_cfg(effects=[{"name": "rotor_reaction_torque"}]), noise_cfg(**QUIET))


def test_stiffness_and_damping_scale_the_model(plate):
    nominal = Simulator(plate, sim_cfg(), noise_cfg(**QUIET))
    stiff = Simulator(plate, sim_cfg(effects=[{"name": "stiffness_scale", "scale": 4.0},
                                              {"name": "damping_scale", "scale": 3.0}]), noise_cfg(**QUIET))
    assert stiff.fem.mu == pytest.approx(4 * plate.fem.mu) and stiff.fem.lam == pytest.approx(4 * plate.fem.lam)
    assert stiff.damping == pytest.approx(3 * plate.damping)
    assert stiff.dt == pytest.approx(nominal.dt / 2, rel=0.1)   # stable step ~ 1/sqrt(E)
    assert plate.fem.mu == nominal.fem.mu                       # the drone is not mutated


def test_imu_bias_offsets_the_reading(plate):
    b = [0.03, 0.0, -0.02]
    sim = Simulator(plate, sim_cfg(effects=[{"name": "imu_bias", "channel": "rot", "value": b}]), noise_cfg(**QUIET))
    st = sim.state(noisy=False)
    assert np.allclose(st.e, [0.03, 0.0, -0.02], atol=1e-3)
    assert np.allclose(st.s, 0.0, atol=1e-9)   # one world-frame tilt on every IMU: no bend
    gyro = Simulator(plate, sim_cfg(effects=[{"name": "imu_bias", "channel": "omega", "value": [0, 0.1, 0]}]),
                     noise_cfg(**QUIET))
    assert gyro.state(noisy=False).e_dot[1] == pytest.approx(0.1)


class Gust(Effect):
    """A user's own effect: a constant upward push on every vertex."""
    name = "gust_up"

    def __init__(self, force: float = 1.0):
        self.force = force

    def body_forces(self, sim, f):
        m = sim.fem.mass
        f[:, 1] += self.force * m / m.sum()


def test_plugin_by_target_and_clear_errors(undamped):
    # float64 unscaled: a push in proportion to the physical mass then moves every node alike
    # (float32 rounding stirs the body at rest by a few 1e-6 relative)
    sim = Simulator(undamped, sim_cfg(gravity=0.0, mass_scaling=0.0, precision="float64",
                                      effects=[{"_target_": "tests.sim.test_effects.Gust", "force": 2.0}]),
                    noise_cfg(**QUIET))
    sim.step(np.zeros(3))
    assert sim.state(noisy=False).p_dot[1] == pytest.approx(2.0 * 0.01, rel=1e-6)
    with pytest.raises(UserError, match="unknown"):
        build_effects([{"name": "rotor_dragg"}])
    with pytest.raises(UserError, match="cannot be imported"):
        build_effects([{"_target_": "nowhere.Effect"}])
    with pytest.raises(UserError, match="rotor_drag"):
        build_effects([{"name": "rotor_drag", "kk": 1.0}])


def test_set_state_replays_the_actuation_chain(plate):
    sim = Simulator(plate, sim_cfg(gravity=0.0, effects=[{"name": "motor_lag", "tau": 0.05}]),
                    noise_cfg(enabled=True, angle_std_deg=0, position_std=0, angle_rate_std_deg=0,
                              velocity_std=0, rotor_std=0, delay=0.02))
    hist = [np.full(3, 1.0)] * 40
    sim.set_state(plate.fem.rest + 1.0, np.zeros_like(plate.fem.rest), np.eye(3), t=2.0, history=hist)
    assert sim.t == 2.0 and np.allclose(sim.x, plate.fem.rest + 1.0)
    assert np.allclose(sim.effects[0].state, 1.0, atol=1e-3)   # the lag has converged on the history
    assert all(np.allclose(q, 1.0) for q in sim._queue)


class Recorder(Effect):
    """Records the lifecycle calls it sees."""
    name = "recorder"

    def __init__(self):
        self.calls = []

    def setup(self, sim):
        self.calls.append(("setup", sim.body is not None))

    def start(self, sim, rng):
        self.calls.append(("start", sim.flight, float(rng.random())))

    def reset(self, sim):
        self.calls.append(("reset",))


def test_lifecycle_setup_sees_the_body_start_once_a_flight_with_its_own_draws(plate):
    rec = Recorder()
    sim = Simulator(plate, sim_cfg(), noise_cfg(**QUIET), seed=5, effects=[rec])
    assert rec.calls[0] == ("setup", True)                 # the body exists at setup
    sim.set_state(plate.fem.rest, np.zeros_like(plate.fem.rest))    # a window: reset, no new draw
    sim.reset()
    sim.reset(flight=0)
    kinds = [c[0] for c in rec.calls]
    assert kinds == ["setup", "start", "reset", "reset", "start", "reset", "start", "reset"]
    starts = [c for c in rec.calls if c[0] == "start"]
    assert [c[1] for c in starts] == [0, 1, 0]
    assert starts[0][2] == starts[2][2] != starts[1][2]      # flight 0 draws the same, flight 1 not
    other = Recorder()
    Simulator(plate, sim_cfg(), noise_cfg(**QUIET), seed=6, effects=[other])
    assert other.calls[1][2] != starts[0][2]                 # another seed, another draw


def test_gusty_wind_is_a_gauss_markov_process_redrawn_per_flight_kept_in_a_window(beam):
    std, T = 1.5, 0.5
    sim = Simulator(beam, sim_cfg(effects=[{"name": "wind", "velocity": [2.0, 0.0], "c": 0.1,
                                            "gust_std": std, "gust_time": T}]), noise_cfg(**QUIET), seed=3)
    wind = sim.effects[0]
    ts = np.arange(0, 400.0, 0.01)
    sim.t = 0.0
    n = np.array([wind.air(type("S", (), {"t": t})) for t in ts])[:, 0] - 2.0
    assert np.std(n) == pytest.approx(std, rel=0.1)
    lag = int(T / 0.01)
    corr = np.corrcoef(n[:-lag], n[lag:])[0, 1]
    assert corr == pytest.approx(np.exp(-1), abs=0.08)       # correlation e^-1 after one time constant
    first = wind.air(type("S", (), {"t": 1.23}))
    sim.set_state(beam.fem.rest, np.zeros_like(beam.fem.rest), t=1.23)
    assert np.array_equal(wind.air(sim), first)              # a window keeps its flight's gusts
    sim.reset()
    assert not np.array_equal(wind.air(type("S", (), {"t": 1.23})), first)   # a new flight draws anew
    with pytest.raises(UserError, match="gust_std"):
        build_effects([{"name": "wind", "gust_std": -1.0}])


def test_a_predicting_simulator_takes_the_gusts_expectation(beam):
    sim = Simulator(beam, sim_cfg(effects=[{"name": "wind", "velocity": [2.0, 0.0], "gust_std": 1.0}]),
                    noise_cfg(**QUIET), draws=False)
    sim.t = 3.0
    assert np.array_equal(sim.effects[0].air(sim), [2.0, 0.0])
