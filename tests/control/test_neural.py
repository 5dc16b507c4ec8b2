"""The neural-controller baseline: trained through a differentiable model (here a point mass
whose answer is known, and random untrained d, g, h), bounded by Tmax, cached atomically."""
import numpy as np
import pytest
import torch

from sdexp.control import neural
from sdexp.config import NeuralControllerConfig
from sdexp.control.neural import NeuralController, Policy, load_or_train_policy, train_policy
from sdexp.control.tasks import Task
from sdexp.model.dynamics import LearnedDynamics
from sdexp.sensing import State
from tests.model.test_dynamics import random_nets

GAIN = 20.0


class PointMass:
    """x = (e, e_dot, px, py, vx, vy), two inputs: p_ddot = GAIN u, e_ddot = -e_dot.
    What train_policy needs of a LearnedDynamics: n, m, slices, dt, parts, dtype, f_torch."""
    n_s, n_e, dim, m, n, dt = 0, 1, 2, 2, 6, 0.01
    slices = dict(s=slice(0, 0), s_dot=slice(0, 0), e=slice(0, 1), e_dot=slice(1, 2), p=slice(2, 4), p_dot=slice(4, 6))
    parts = []
    dtype = torch.float64

    def f_torch(self, x, u):
        return torch.cat([x[..., 1:2], -x[..., 1:2], x[..., 4:6], GAIN * u], -1)


def cfg(**kw):
    c = dict(hidden=16, layers=1, iterations=40, batch=16, horizon=15, lr=3e-2, goal_radius=0.3,
             w_att=1.0, w_bend=0.1, w_vel=0.05, w_u=0.01)
    c.update(kw)
    return NeuralControllerConfig(**c)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def trained_point_mass():
    torch.set_num_threads(1)
    data_x = np.random.default_rng(0).normal(size=(200, 6)) * 0.1
    return train_policy(PointMass(), data_x, 1.0, cfg(), seed=0, progress=False)


def test_training_lowers_the_loss(trained_point_mass):
    policy, losses = trained_point_mass
    assert len(losses) == 40 and np.all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5])


def test_trained_policy_pushes_towards_the_goal(trained_point_mass):
    """From rest, the command (= acceleration / GAIN) points at the goal."""
    policy, _ = trained_point_mass
    rng = np.random.default_rng(1)
    goals = rng.normal(size=(64, 2))
    goals *= 0.25 / np.linalg.norm(goals, axis=1, keepdims=True)
    with torch.no_grad():
        u = policy(torch.zeros(64, 6), torch.as_tensor(goals, dtype=torch.float32)).numpy()
    cos = (u * goals).sum(1) / (np.linalg.norm(u, axis=1) * 0.25)
    assert np.mean(cos > 0.5) > 0.9


def test_policy_is_bounded_translation_invariant_and_wraps_attitude(trained_point_mass):
    policy, _ = trained_point_mass
    tmax = policy.max_thrust
    assert tmax == 1.0
    rng = np.random.default_rng(2)
    x = torch.as_tensor(rng.normal(size=(32, 6)) * 1e3, dtype=torch.float32)
    g = torch.as_tensor(rng.normal(size=(32, 2)) * 1e3, dtype=torch.float32)
    with torch.no_grad():
        u = policy(x, g)
        assert u.abs().max() <= tmax and u.abs().max() > 0.9 * tmax
        x = torch.as_tensor(rng.normal(size=(32, 6)) * 0.2, dtype=torch.float32)
        g = torch.as_tensor(rng.normal(size=(32, 2)) * 0.2, dtype=torch.float32)
        shift = torch.tensor([0.0, 0.0, 5.0, -3.0, 0.0, 0.0])
        np.testing.assert_allclose(policy(x + shift, g + shift[2:4]), policy(x, g), atol=1e-5)
        turn = torch.tensor([2 * np.pi, 0.0, 0.0, 0.0, 0.0, 0.0])
        np.testing.assert_allclose(policy(x + turn, g), policy(x, g), atol=1e-4)
        # and it does depend on the attitude and on the goal
        assert (policy(x + 0.5 * turn / np.pi, g) - policy(x, g)).abs().max() > 1e-3
        assert (policy(x, g + 0.1) - policy(x, g)).abs().max() > 1e-3


def test_neural_controller_acts_on_the_moving_goal(trained_point_mass):
    policy, _ = trained_point_mass
    ctl = NeuralController(policy)
    task = Task(start=np.zeros(2), target=[0.1, 0.0], seconds=1.0, n_s=0, velocity=[0.0, 0.5])
    ctl.reset(task)
    st = State(np.zeros(0), np.array([0.1]), np.array([0.05, 0.0]), np.zeros(0), np.zeros(1), np.zeros(2))
    for t in (0.0, 0.4):
        u = ctl.act(t, st)
        assert u.dtype == np.float64 and u.shape == (2,)
        with torch.no_grad():
            want = policy(torch.as_tensor(st.x, dtype=torch.float32), torch.tensor([0.1, 0.5 * t], dtype=torch.float32))
        np.testing.assert_allclose(u, want.numpy(), rtol=1e-6)
    assert not np.allclose(ctl.act(0.0, st), ctl.act(0.4, st))


@pytest.fixture(scope="module")
def random_dyn():
    return LearnedDynamics(random_nets(2, 1, 2, 3, hidden=8, blocks=1), 2, 1, 2, 3, 0.01)


def test_trains_through_learned_networks_without_touching_them(random_dyn):
    dyn = random_dyn
    before = {k: v.clone() for _, net, _, _ in dyn.parts for k, v in net.state_dict().items()}
    data_x = np.random.default_rng(0).normal(size=(50, dyn.n))
    policy, losses = train_policy(dyn, data_x, 4.0, cfg(iterations=3, batch=8, horizon=5), seed=0, progress=False)
    assert len(losses) == 3 and np.all(np.isfinite(losses))
    assert dyn.dtype == torch.float64                       # the float32 copy is a copy
    after = {k: v for _, net, _, _ in dyn.parts for k, v in net.state_dict().items()}
    for k in before:
        assert torch.equal(before[k], after[k])
    with torch.no_grad():
        u = policy(torch.as_tensor(data_x * 100, dtype=torch.float32), torch.zeros(50, 2))
    assert u.shape == (50, 3) and u.abs().max() <= 4.0
    # same seed, same policy
    policy2, losses2 = train_policy(dyn, data_x, 4.0, cfg(iterations=3, batch=8, horizon=5), seed=0, progress=False)
    assert losses2 == losses
    for a, b in zip(policy.state_dict().values(), policy2.state_dict().values()):
        assert torch.equal(a, b)


def test_policy_cache_round_trip(random_dyn, tmp_path, monkeypatch, caplog):
    dyn = random_dyn
    data_x = np.random.default_rng(0).normal(size=(50, dyn.n))
    c = cfg(iterations=2, batch=8, horizon=4)
    policy, losses = load_or_train_policy(dyn, data_x, 4.0, c, 0, "nets-abc", tmp_path, progress=False)
    files = sorted(p.name for p in tmp_path.iterdir() if p.name != ".locks")   # .locks: the build locks
    assert len(files) == 1 and files[0].startswith("policy-") and files[0].endswith(".pt")   # no temp left
    # a second call loads, never trains
    def no_training(*a, **k):
        raise AssertionError("trained again instead of loading the cache")

    monkeypatch.setattr(neural, "train_policy", no_training)
    loaded, losses2 = load_or_train_policy(dyn, data_x, 4.0, c, 0, "nets-abc", tmp_path, progress=False)
    assert isinstance(loaded, Policy) and not loaded.training
    assert losses2 == losses
    for (k, a), (k2, b) in zip(policy.state_dict().items(), loaded.state_dict().items()):
        assert k == k2 and torch.equal(a, b)
    x = torch.as_tensor(data_x, dtype=torch.float32)
    with torch.no_grad():
        assert torch.equal(policy(x, torch.zeros(50, 2)), loaded(x, torch.zeros(50, 2)))
    # another seed, config or network is another entry
    with pytest.raises(AssertionError, match="trained again"):
        load_or_train_policy(dyn, data_x, 4.0, c, 1, "nets-abc", tmp_path, progress=False)
    with pytest.raises(AssertionError, match="trained again"):
        load_or_train_policy(dyn, data_x, 4.0, c, 0, "nets-xyz", tmp_path, progress=False)
    with pytest.raises(AssertionError, match="trained again"):
        load_or_train_policy(dyn, data_x, 4.0, cfg(iterations=2, batch=8, horizon=5), 0, "nets-abc", tmp_path,
                             progress=False)
    # an unreadable entry is retrained and replaced, not an error
    monkeypatch.undo()
    (tmp_path / files[0]).write_bytes(b"not a torch file")
    again, losses3 = load_or_train_policy(dyn, data_x, 4.0, c, 0, "nets-abc", tmp_path, progress=False)
    assert "unreadable" in caplog.text
    assert losses3 == losses
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != ".locks") == files
