"""The soft drones as Gymnasium environments (sdexp.envs): the checker, without a warning, on every
task of the cheap drones (every registered env: -m slow), normalised actions and bounded
observations, reproducible resets, the loss-of-control rule, truncation at the task's duration,
vector envs (one process per core), pictures and videos of an episode, ours as a policy that flies
in the env exactly as fly() flies it, and bad keywords as one-line errors."""
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sdexp.envs
from sdexp.envs.tasks import TASKS
from sdexp.errors import UserError
from tests.eval.references import SHRUNK

CHEAP = ("rod", "engine")   # 2D, under 100 quadratic triangles: milliseconds a step


def make(env_id, cache_dir, *overrides, **kw):
    return gym.make(env_id, overrides=[f"cache_dir={cache_dir}", *overrides], **kw)


HOVER = 9.81 / 5 / 10   # the rod's even hover thrust as a fraction of Tmax (1 kg, 5 rotors of 10 N)


def checked(env):
    """Gymnasium's checker with every warning an error (its advice too: a normalised action space,
    finite observation bounds), the render mode it makes an env for included."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)


def test_every_drone_and_task_is_registered():
    from sdexp import conf
    ids = sdexp.envs.env_ids()
    assert len(ids) == len(conf.paper_drones()) * len(TASKS) == 48
    assert {"sdexp/Rod-Hover-v0", "sdexp/Flower-Reach-v0", "sdexp/OrangePeel-Deform-v0",
            "sdexp/Star-Velocity-v0"} <= set(ids) <= set(gym.registry)


@pytest.mark.parametrize("drone", CHEAP)
@pytest.mark.parametrize("task", TASKS)
def test_the_checker_passes_on_the_cheap_drones(drone, task, cache_dir):
    checked(make(sdexp.envs.env_id(drone, task), cache_dir))


@pytest.mark.slow
@pytest.mark.parametrize("env_id", sorted(sdexp.envs.env_ids()))
def test_the_checker_passes_on_every_registered_env(env_id, cache_dir):
    checked(make(env_id, cache_dir))


def test_spaces_are_the_decomposed_state_and_the_thrusts(cache_dir):
    env = make("sdexp/Rod-Hover-v0", cache_dir)
    base = env.unwrapped
    n = 2 * (8 + 1 + 2)                              # (s, e, p) and rates: 8 bends, 1 angle, 2D position
    assert env.observation_space.shape == (2 * n,) and base.n == n
    assert env.action_space.shape == (5,) and np.all(env.action_space.high == 1.0)   # x Tmax = 10 N
    obs, info = env.reset(seed=0)
    assert np.allclose(obs[base.slices["p"]], 0.0, atol=0.05)      # released at the task's start (noisy)
    assert np.array_equal(obs[n:], base.task.goal(0.0).x.astype(np.float32))
    # bounded: angles by pi, the position by the arena (10 m) and a metre, the speed by the thrust
    low, high = env.observation_space.low, env.observation_space.high
    sl = base.slices
    assert np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.array_equal(high[:n], high[n:])
    assert np.allclose(high[sl["s"]], np.pi) and np.allclose(high[sl["p"]], 11) and np.allclose(low[sl["p"]], -11)
    assert 30 < high[sl["p_dot"]][0] < 100


def test_the_action_is_a_fraction_of_the_thrust_or_the_thrust_in_newtons(cache_dir):
    """The same thrusts, 0.5 x Tmax by default or 5 N with action_scale=newtons, fly the same."""
    normalised = make("sdexp/Rod-Hover-v0", cache_dir)
    newtons = make("sdexp/Rod-Hover-v0", cache_dir, action_scale="newtons")
    assert np.all(newtons.action_space.high == 10.0)
    a, b = normalised.reset(seed=1)[0], newtons.reset(seed=1)[0]
    for _ in range(5):
        a, b = normalised.step(np.full(5, 0.5, np.float32))[0], newtons.step(np.full(5, 5.0, np.float32))[0]
    assert np.array_equal(a, b)


def test_observations_past_the_bounds_are_clipped_to_them(cache_dir):
    env = make("sdexp/Rod-Hover-v0", cache_dir, "flight.arena_margin=0.5")
    base = env.unwrapped
    assert np.allclose(env.observation_space.high[base.slices["p"]], 1.5)
    env.reset(seed=0)
    for _ in range(200):   # no thrust: the rod falls out of the half-metre arena
        obs, _, terminated, _, info = env.step(np.zeros(5, np.float32))
        if terminated:
            break
    assert terminated and info["failure"].startswith("loss_of_control: left the arena") and obs in env.observation_space


def test_a_seeded_reset_repeats_the_episode_bit_for_bit_and_seeds_differ(cache_dir):
    env, fresh = make("sdexp/Rod-Hover-v0", cache_dir), make("sdexp/Rod-Hover-v0", cache_dir)
    actions = np.random.default_rng(0).uniform(-1, 1, (20, 5)).astype(np.float32)

    def episode(env, seed):
        """Every observation, reward and the noise-free state at the end, as bytes."""
        obs, rewards = [env.reset(seed=seed)[0]], []
        for a in actions:
            o, r, *_ = env.step(a)
            obs.append(o)
            rewards.append(r)
        return np.array(obs).tobytes() + np.array(rewards).tobytes() + env.unwrapped.sim.state(noisy=False).x.tobytes()
    a, b, c, d = episode(env, 3), episode(env, 3), episode(fresh, 3), episode(env, 4)
    assert a == b == c and a != d        # the sensor and rotor noise are the seed's


def test_the_episode_is_truncated_at_the_tasks_duration(cache_dir):
    env = make("sdexp/Rod-Hover-v0", cache_dir, seconds=0.05)
    env.reset(seed=0)
    hover = np.full(5, HOVER, np.float32)
    flags = [env.step(hover)[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(False, True)]


def test_a_flip_terminates_by_the_loss_of_control_rule(cache_dir):
    env = make("sdexp/Rod-Hover-v0", cache_dir, "flight.max_tilt_deg=20")
    env.reset(seed=0)
    lopsided = np.array([1, 1, 0, -1, -1], np.float32)    # a torque that rolls the rod over
    for k in range(300):
        _, reward, terminated, truncated, info = env.step(lopsided)
        if terminated:
            break
    assert terminated and not truncated and info["failure"].startswith("loss_of_control: tilt")
    assert 0 < reward <= 1


def test_the_task_keywords_shape_the_goal(cache_dir):
    reach = make("sdexp/Rod-Reach-v0", cache_dir).unwrapped
    assert np.allclose(reach.task.target, [3, 3]) and reach.max_steps == 2000
    vel = make("sdexp/Rod-Velocity-v0", cache_dir, velocity=[1.0, 0.0], seconds=2).unwrapped
    assert np.allclose(vel.task.goal(2.0).p, [2, 0]) and vel.max_steps == 200
    deform = make("sdexp/Rod-Deform-v0", cache_dir, angle_deg=10).unwrapped
    assert deform.task.seconds == 17 and np.isclose(np.rad2deg(deform.task.bend(7.0)).max(), 10)


@pytest.mark.parametrize("kw, message", [
    ({"task_kw": {"angle_deg": 5}, "env": "sdexp/Rod-Hover-v0"}, "'angle_deg' does not apply to the hover task"),
    ({"task_kw": {"target": [1, 2, 3]}, "env": "sdexp/Rod-Reach-v0"}, r"target = \[1, 2, 3\]: allowed 2 finite numbers"),
    ({"task_kw": {"seconds": -1}, "env": "sdexp/Rod-Hover-v0"}, "seconds = -1.0 is out of range: allowed > 0"),
    ({"task_kw": {"overrides": ["drone.youngs_modulus=-3"]}, "env": "sdexp/Rod-Hover-v0"}, "drone.youngs_modulus"),
    ({"task_kw": {"overrides": ["sim.elemnt=linear"]}, "env": "sdexp/Rod-Hover-v0"}, "sim.elemnt"),
    ({"task_kw": {"action_scale": "raw"}, "env": "sdexp/Rod-Hover-v0"},
     "action_scale = 'raw' is unknown: choose one of normalized, newtons"),
    ({"task_kw": {"render_mode": "rgb"}, "env": "sdexp/Rod-Hover-v0"},
     "render_mode = 'rgb' is unknown: choose one of None, rgb_array"),
])
def test_bad_keywords_are_one_line_errors(kw, message, cache_dir):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # gymnasium's own warning of a render mode it does not know
        with pytest.raises(UserError, match=message) as err:
            gym.make(kw["env"], **kw["task_kw"])
    assert "\n" not in str(err.value)


def test_vector_envs_step_in_sync_and_in_processes(cache_dir):
    """gymnasium's sync vector env, and sdexp.envs.make_vec: one spawned process per env."""
    from sdexp.parallel import available_cores
    sync = gym.make_vec("sdexp/Rod-Hover-v0", num_envs=2, vectorization_mode="sync",
                        overrides=[f"cache_dir={cache_dir}"], seconds=0.03)
    spawned = sdexp.envs.make_vec("sdexp/Rod-Hover-v0", 2, overrides=[f"cache_dir={cache_dir}"], seconds=0.03)
    assert isinstance(spawned, gym.vector.AsyncVectorEnv) and available_cores() >= 1
    for envs in (sync, spawned):
        obs, _ = envs.reset(seed=[1, 2])
        assert obs.shape == (2, 44) and not np.allclose(obs[0], obs[1])
        for _ in range(3):
            obs, reward, terminated, truncated, info = envs.step(np.full((2, 5), HOVER, np.float32))
        assert list(truncated) == [True, True] and reward.shape == (2,)   # and auto-reset next step
        envs.close()


@pytest.mark.parametrize("num_envs", [0, -1, 1.5, True, "2"])
def test_a_bad_number_of_envs_names_the_key_and_the_range(num_envs):
    with pytest.raises(UserError, match=r"num_envs = .* is out of range: allowed an integer >= 1 \(default \d+: "
                                        r"the cores this process may use\)"):
        sdexp.envs.make_vec("sdexp/Rod-Hover-v0", num_envs)


def test_render_draws_the_drone_and_record_video_writes_the_episode(cache_dir, tmp_path):
    env = make("sdexp/Rod-Hover-v0", cache_dir, render_mode="rgb_array", seconds=0.1)
    assert env.render_mode == "rgb_array" and env.metadata["render_fps"] == 100
    env = gym.wrappers.RecordVideo(env, str(tmp_path / "videos"), name_prefix="rod", disable_logger=True)
    env.reset(seed=0)
    first = env.render()
    done = False
    while not done:   # 10 steps; the rod sags and tips under a lopsided thrust
        _, _, terminated, truncated, _ = env.step(np.array([1, 0.5, 0, 0, 0], np.float32))
        done = terminated or truncated
    last = env.render()
    env.close()
    assert first.shape == (480, 640, 3) and first.dtype == np.uint8 and not np.array_equal(first, last)
    (video,) = (tmp_path / "videos").glob("*")
    assert video.stat().st_size > 1000


def test_ours_flies_in_the_env_as_fly_flies_it(cache_dir):
    """Noise off, so that both are deterministic: the env's episode under OursPolicy ends where
    sdexp's own flight loop (control.rollout.fly) ends the same task, to the float32 of the
    observation."""
    from sdexp.envs.policy import OursPolicy
    from sdexp.eval.flights import Setup
    overrides = [*SHRUNK[1:], f"cache_dir={cache_dir}", "noise.enabled=false"]
    env = gym.make("sdexp/Rod-Reach-v0", overrides=overrides, seconds=0.3, target=[1, 1])
    policy = OursPolicy(env, progress=False)
    obs, _ = env.reset(seed=0)
    policy.reset()
    done, rewards = False, []
    while not done:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        rewards.append(reward)
        done = terminated or truncated
    assert truncated and len(rewards) == 30
    base = env.unwrapped
    setup = Setup(base.cfg, progress=False)
    sim = setup.simulator()
    flight, m = setup.fly(sim, setup.controller("ours", sim), setup.task([0, 0], [1, 1], 0.3))
    assert info["position_error"] == pytest.approx(m["final_error"], abs=1e-5)
    assert np.allclose(base.sim.state(noisy=False).x, flight.x[-1], atol=1e-5)
    # predict(), Stable-Baselines3's signature, is the same controller
    obs, _ = env.reset(seed=0)
    first, _ = policy.predict(obs[None], episode_start=np.array([True]))
    policy.reset()
    assert np.array_equal(first[0], policy(obs))


def test_a_riccati_failure_of_ours_ends_the_episode_as_a_controller_failure(cache_dir, monkeypatch):
    """As in fly(): no stabilising gain is a recorded failure, not an exception out of predict()."""
    from sdexp.control.lqr import LqrFailure
    from sdexp.control.relinearizing import RelinearizingLQR
    from sdexp.envs.policy import OursPolicy

    def no_gain(self, t, state):
        raise LqrFailure("the Riccati solution does not solve the equation (ill-posed)")
    monkeypatch.setattr(RelinearizingLQR, "act", no_gain)
    env = gym.make("sdexp/Rod-Hover-v0", overrides=[*SHRUNK[1:], f"cache_dir={cache_dir}"], seconds=0.3)
    policy = OursPolicy(env, progress=False)
    obs, _ = env.reset(seed=0)
    policy.reset()
    action = policy(obs)
    assert np.isnan(action).all()
    _, _, terminated, _, info = env.step(action)
    assert terminated and info["failure"] == "controller: non-finite command"


def test_the_benchmark_reports_steps_per_second_on_one_and_two_cores(cache_dir):
    from sdexp.envs.bench import main
    (row,) = main(["--drones", "rod", "--steps", "20", "--override", f"cache_dir={cache_dir}"])
    assert row["env"] == "sdexp/Rod-Hover-v0"
    assert row["steps_per_s_1_core"] > 0 and row["steps_per_s_2_cores"] > 0    # timings: never asserted
