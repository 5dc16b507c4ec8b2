"""LearnedDynamics: Eq. 4, its Jacobians (Eq. 6) against finite differences and in block form,
explicit steps; and the model_test / ablation_decomposition experiments run shrunk."""

import numpy as np
import pandas as pd
import pytest
import torch

from sdexp.model.dynamics import LearnedDynamics, state_sizes
from sdexp.model.networks import ResidualMLP
from sdexp.model.specs import DECOMPOSED
from sdexp.model.training import design
from tests.model.test_networks import synthetic_dataset
from tests.eval.references import SHRUNK  # one shrunk model for every experiment test

ALPHA = 0.01


def random_nets(n_s, n_e, dim, m, hidden=32, blocks=2, seed=0):
    """Untrained d, g, h with non-trivial scaling buffers, wired as DECOMPOSED says."""
    torch.manual_seed(seed)
    sizes = {"s": n_s, "s_dot": n_s, "e": n_e, "e_dot": n_e, "p": dim, "p_dot": dim, "u": m}
    nets = {}
    for spec in DECOMPOSED:
        if sizes[spec.current] == 0:
            continue
        n_in = sum(sizes[k] for k in spec.inputs)
        off = sum(sizes[k] for k in spec.inputs[: spec.inputs.index(spec.current)])
        net = ResidualMLP(n_in, sizes[spec.current], hidden, blocks, list(range(off, off + sizes[spec.current])))
        with torch.no_grad():
            net.in_mean.uniform_(-0.5, 0.5)
            net.in_std.uniform_(0.5, 2.0)
            net.out_mean.uniform_(-0.1, 0.1)
            net.out_std.uniform_(0.05, 0.3)
        nets[spec.name] = net.eval()
    return nets


@pytest.fixture(scope="module")
def flower_dyn():
    return LearnedDynamics(random_nets(8, 3, 3, 9), 8, 3, 3, 9, ALPHA)


def point(dyn, seed=1):
    rng = np.random.default_rng(seed)
    return rng.normal(size=dyn.n), rng.uniform(-1, 1, dyn.m)


def test_f_is_eq4(flower_dyn):
    dyn = flower_dyn
    x, u = point(dyn)
    sl = dyn.slices
    s, s_dot, e, e_dot, p, p_dot = (x[sl[k]] for k in ("s", "s_dot", "e", "e_dot", "p", "p_dot"))
    nets = {name: net.double() for name, net in random_nets(8, 3, 3, 9).items()}
    call = lambda name, *parts: nets[name](torch.tensor(np.concatenate(parts))).detach().numpy()
    d = call("d", s, s_dot, u)
    g = call("g", s, s_dot, e, e_dot, u)
    h = call("h", s, s_dot, e, e_dot, p_dot, u)
    expect = np.concatenate([s_dot, (d - s_dot) / ALPHA, e_dot, (g - e_dot) / ALPHA, p_dot, (h - p_dot) / ALPHA])
    np.testing.assert_allclose(dyn.f(x, u), expect, rtol=1e-10, atol=1e-10)
    # f does not depend on p (no network reads it)
    x2 = x.copy()
    x2[sl["p"]] += 5.0
    np.testing.assert_array_equal(dyn.f(x2, u), dyn.f(x, u))


def test_f_hand_case():
    """Output layers zeroed: every network returns current + out_mean, so the accelerations are
    out_mean / alpha exactly, whatever the state."""
    nets = random_nets(2, 1, 2, 3)
    consts = {"d": [0.3, -0.2], "g": [0.05], "h": [0.0, -0.0981]}
    for name, net in nets.items():
        with torch.no_grad():
            net.out.weight.zero_()
            net.out.bias.zero_()
            net.out_mean[:] = torch.tensor(consts[name])
    dyn = LearnedDynamics(nets, 2, 1, 2, 3, ALPHA)
    x = np.array([0.1, -0.1, 1.0, 2.0, 0.5, -0.5, 3.0, 4.0, 5.0, 6.0])   # s(2) s_dot(2) e e_dot p(2) p_dot(2)
    f = dyn.f(x, np.zeros(3))
    np.testing.assert_allclose(f, [1.0, 2.0, 30.0, -20.0, -0.5, 5.0, 5.0, 6.0, 0.0, -9.81], rtol=1e-6, atol=1e-9)


def test_batched_f(flower_dyn):
    dyn = flower_dyn
    rng = np.random.default_rng(2)
    X, U = rng.normal(size=(7, dyn.n)), rng.normal(size=(7, dyn.m))
    F = dyn.f(X, U)
    assert F.shape == (7, dyn.n)
    for i in range(7):
        np.testing.assert_allclose(F[i], dyn.f(X[i], U[i]), rtol=1e-12, atol=1e-12)


def test_jacobians_match_central_differences(flower_dyn):
    dyn = flower_dyn
    for seed in (1, 2, 3):
        x, u = point(dyn, seed)
        A, B = dyn.jacobians(x, u)
        assert A.shape == (28, 28) and B.shape == (28, 9)
        h = 1e-6
        Af = np.stack([(dyn.f(x + h * ei, u) - dyn.f(x - h * ei, u)) / (2 * h) for ei in np.eye(dyn.n)], axis=1)
        Bf = np.stack([(dyn.f(x, u + h * ei) - dyn.f(x, u - h * ei)) / (2 * h) for ei in np.eye(dyn.m)], axis=1)
        scale = np.abs(A).max()
        np.testing.assert_allclose(A, Af, atol=1e-6 * scale)
        np.testing.assert_allclose(B, Bf, atol=1e-6 * np.abs(B).max())
        f0, A2, B2 = dyn.linearize(x, u)
        np.testing.assert_allclose(f0, dyn.f(x, u), rtol=1e-12, atol=1e-10)
        np.testing.assert_array_equal(A2, A)


def test_jacobians_have_the_eq6_block_structure(flower_dyn):
    dyn = flower_dyn
    A, B = dyn.jacobians(*point(dyn))
    idx = {k: np.arange(dyn.n + dyn.m)[sl] for k, sl in dyn.slices.items()}
    blk = lambda M, r, c: M[np.ix_(idx[r], idx[c])]
    order = ("s", "s_dot", "e", "e_dot", "p", "p_dot")
    # position rows: exactly [0 .. I .. 0] with I on the matching velocity; no u
    for pos, vel in (("s", "s_dot"), ("e", "e_dot"), ("p", "p_dot")):
        for c in order:
            expect = np.eye(len(idx[pos])) if c == vel else np.zeros((len(idx[pos]), len(idx[c])))
            np.testing.assert_array_equal(blk(A, pos, c), expect)
        assert not B[idx[pos]].any()
    # velocity rows: zero exactly where the input does not feed the network
    zero = {"s_dot": ("e", "e_dot", "p", "p_dot"), "e_dot": ("p", "p_dot"), "p_dot": ("p",)}
    feeds = {"s_dot": ("s", "s_dot"), "e_dot": ("s", "s_dot", "e", "e_dot"), "p_dot": ("s", "s_dot", "e", "e_dot", "p_dot")}
    for row in zero:
        for c in zero[row]:
            assert not blk(A, row, c).any(), (row, c)
        for c in feeds[row]:
            assert np.abs(blk(A, row, c)).max() > 0, (row, c)
        assert np.abs(B[idx[row]]).max() > 0
    # the (1/alpha)(dd/ds_dot - I) diagonal: an untrained residual net keeps d ~ s_dot + small
    assert np.all(np.diag(blk(A, "s_dot", "s_dot")) < 0.5 / ALPHA)


def test_drone_without_peripheral_sensors():
    nets = random_nets(0, 3, 3, 4)
    assert "d" not in nets
    dyn = LearnedDynamics(nets, 0, 3, 3, 4, ALPHA)
    x, u = point(dyn)
    A, B = dyn.jacobians(x, u)
    assert A.shape == (12, 12) and B.shape == (12, 4)


def test_dynamics_from_trained_nets_and_rollouts():
    from sdexp.eval.model_test import acceleration_test, rollout, state_errors
    from sdexp.model.training import train_models
    from tests.model.test_networks import model_cfg

    data = synthetic_dataset(n=3000, n_s=2, n_e=1, dim=2, m=3)
    trained = train_models(data, model_cfg(epochs=4), 0, None, 0.2, progress=False)
    dyn = LearnedDynamics.from_trained(trained, data, ALPHA)
    assert (dyn.n_s, dyn.n_e, dyn.dim, dyn.m) == (2, 1, 2, 3) and state_sizes(data)["m"] == 3
    # dynamics' velocity prediction is the trained net's, in float64
    X, Y, _ = design(data, DECOMPOSED[0], np.arange(5))
    a = data.arrays
    x = np.concatenate([a[k][:5] for k in ("s", "s_dot", "e", "e_dot", "p", "p_dot")], axis=1)
    nxt = x[:, dyn.slices["s_dot"]] + ALPHA * dyn.f(x, a["u"][:5])[:, dyn.slices["s_dot"]]
    with torch.no_grad():
        np.testing.assert_allclose(nxt, trained.nets["d"](torch.from_numpy(X)).numpy(), rtol=1e-4, atol=1e-5)
    # R^2 of the reconstructed acceleration is high on a learnable system
    _, val = data.split(0.2, 0)
    table, _, rows = acceleration_test(data, trained, val, ALPHA)
    np.testing.assert_array_equal(rows, val)
    # k-frame targets: only the rows that have one (same episode, same held command), over k frames
    from dataclasses import replace
    from sdexp.model.training import horizon_rows
    held = replace(data, arrays={**data.arrays, "u": data.arrays["u"][np.arange(len(data)) // 10 * 10]})
    _, series3, rows3 = acceleration_test(held, trained, val, 3 * ALPHA, 3)
    np.testing.assert_array_equal(rows3, np.intersect1d(horizon_rows(held.arrays, 3), val))
    assert 0.7 * len(val) < len(rows3) < len(val) and len(series3["s"][0]) == len(rows3)
    assert len(table) == 2 + 1 + 2 and table["r2"].min() > 0.5 and (table["r2_no_change"] < 0.1).all()
    # relinearising every step follows the nonlinear model closely over a short horizon
    U = np.random.default_rng(0).uniform(-1, 1, (20, 3))
    X_nl, _ = rollout(dyn, x[0], U, 1, linear=False)
    X_l1, times = rollout(dyn, x[0], U, 1, linear=True)
    X_l5, _ = rollout(dyn, x[0], U, 5, linear=True)
    assert len(times) == 20 and np.isfinite(X_l5).all()
    err = state_errors(dyn, X_l1, X_nl)
    assert max(v.max() for v in err.values()) < 1e-6
    # restarts from the truth: zero error right at the start
    X_hz, _ = rollout(dyn, x[0], U, 5, linear=True, X_true=X_nl, restart=10)
    np.testing.assert_array_equal(X_hz[0], X_nl[0])


# ------------------------------------------------------------------------------ experiments, shrunk

def _run_or_skip(tmp_path, cache_dir, *overrides):
    from sdexp.eval.run import run_experiment
    from tests.conftest import make_cfg

    cfg = make_cfg(*SHRUNK, f"cache_dir={cache_dir}", *overrides)
    try:
        return run_experiment(cfg, tmp_path)
    except NotImplementedError:
        pytest.skip("sdexp.model.dataset.load_dataset is not implemented yet")


def test_model_test_runs_shrunk(tmp_path, cache_dir):
    metrics = _run_or_skip(tmp_path, cache_dir, "experiment=model_test", "experiment.params.rollout_seconds=1.5",
                           "experiment.params.horizon_seconds=0.2", "experiment.params.plot_seconds=0.5")
    for f in ("training.csv", "training.png", "acceleration_r2.csv", "acceleration.png", "rollout.csv",
              "rollout_horizon.csv", "rollout.png", "input_jacobian.csv", "bench_model.csv", "metrics.json"):
        assert (tmp_path / f).exists(), f
    bench = pd.read_csv(tmp_path / "bench_model.csv").set_index("item")
    assert bench.loc["dataset", "samples_per_second"] > 0 and bench.loc["dataset", "samples"] > 0
    assert all(bench.loc[f"train {n}", "seconds"] > 0 for n in ("d", "g", "h"))
    assert metrics["flight_source"].startswith("simulated")   # episodes are 1 s, the flight 1.5 s
    assert metrics["flight_seconds"] > 0.5 and metrics["jacobians_ms_mean"] > 0
    assert np.isfinite(metrics["r2_mean"]) and "rollout_linearized_p_err_1s" in metrics
    for k in (1, 10):   # the rod's learned B against the simulator's, per velocity block
        assert 0 <= metrics[f"input_jacobian_p_dot_{k}step_sign_agreement"] <= 1
        assert np.isfinite(metrics[f"input_jacobian_s_dot_{k}step_rel_error"])


def test_ablation_decomposition_runs_shrunk(tmp_path, cache_dir):
    metrics = _run_or_skip(tmp_path, cache_dir, "experiment=ablation_decomposition")
    assert (tmp_path / "ablation_decomposition.csv").exists() and (tmp_path / "ablation_decomposition.png").exists()
    assert metrics["all_ratio_undecomposed_over_decomposed"] > 0 and metrics["shared_ratio_best"] > 0
    assert metrics["undecomposed_channels"] == 2 + 1 + 8   # rod: p (2), e (1), 8 peripheral angles


@pytest.mark.parametrize("base,hidden,prior", [(True, 24, False), (False, 24, False), (True, 0, False), (True, 24, True)])
def test_hand_reverse_pass_equals_torch_autograd(base, hidden, prior):
    """The relinearisation's Jacobian pass (by hand, for speed) is exact reverse-mode
    differentiation: it equals torch.autograd on the same float64 network (hidden = 0: a
    linear one, model.linear; prior: with a fixed affine map added, model.prior)."""
    from sdexp.model.dynamics import _MlpJacobian

    torch.manual_seed(3)
    net = ResidualMLP(11, 4, hidden=hidden, blocks=4, base=[2, 3, 4, 5] if base else None, prior=prior).double()
    with torch.no_grad():
        net.in_mean.uniform_(-0.5, 0.5); net.in_std.uniform_(0.5, 2.0)
        net.out_mean.uniform_(-0.1, 0.1); net.out_std.uniform_(0.05, 0.3)
    if prior:
        net.set_prior(np.random.default_rng(5).normal(size=(4, 11)), [0.1, -0.2, 0.3, 9.81])
    jac = _MlpJacobian(net)
    for z in np.random.default_rng(4).normal(size=(5, 11)):
        y, J = jac(z)
        zt = torch.tensor(z)
        np.testing.assert_allclose(y, net(zt).detach().numpy(), rtol=1e-12, atol=1e-12)
        J_ref = torch.autograd.functional.jacobian(net, zt).numpy()
        np.testing.assert_allclose(J, J_ref, rtol=1e-10, atol=1e-12)


def test_model_test_tests_multi_frame_networks_on_their_own_targets(tmp_path, cache_dir):
    """model.horizon = 5 (the controllers' recipe): alpha is 5 control intervals, only rows with
    a 5-frame target are scored, and the rollout still steps one control interval."""
    metrics = _run_or_skip(tmp_path, cache_dir, "experiment=model_test", "model.horizon=5",
                           "experiment.params.rollout_seconds=1.5", "experiment.params.horizon_seconds=0.2",
                           "experiment.params.plot_seconds=0.5")
    table = pd.read_csv(tmp_path / "acceleration_r2.csv")
    assert np.isfinite(table["r2"]).all() and (tmp_path / "acceleration.png").exists()
    assert metrics["flight_seconds"] == pytest.approx(1.5)
    assert np.allclose(np.diff(pd.read_csv(tmp_path / "rollout.csv")["t"]), 0.01)


def test_an_ensemble_is_the_mean_of_its_members():
    """model.ensemble: f, A and B of an ensemble's dynamics are the means of its members' (f is
    linear in the nets' outputs), through the hand Jacobian pass and through torch alike."""
    from sdexp.model.networks import EnsembleMLP

    members = [random_nets(8, 3, 3, 9, seed=k) for k in range(3)]
    dyns = [LearnedDynamics(n, 8, 3, 3, 9, ALPHA) for n in members]
    mean = LearnedDynamics({name: EnsembleMLP([n[name] for n in members]) for name in members[0]}, 8, 3, 3, 9, ALPHA)
    x, u = point(mean)
    f, A, B = mean.linearize(x, u)
    parts = [d.linearize(x, u) for d in dyns]
    for got, k in ((f, 0), (A, 1), (B, 2)):
        np.testing.assert_allclose(got, np.mean([p[k] for p in parts], axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(mean.f(x, u), f, rtol=1e-12, atol=1e-12)
    assert not np.allclose(parts[0][1], parts[1][1])   # the members differ: the mean is not any one
    with pytest.raises(ValueError, match="same shape"):
        EnsembleMLP([members[0]["d"], members[0]["g"]])


def test_ensemble_members_train_from_their_own_seeds(tmp_path):
    """Member 0 trains from the run's seed (the nets of ensemble 1, from the same cache entry),
    the others from seeds of their own; the ensemble's nets are their means."""
    from sdexp.model.training import ensemble, member_seed, train_models
    from tests.model.test_networks import model_cfg

    data = synthetic_dataset(n=1500, n_s=2, n_e=1, dim=2, m=3)
    cfg = model_cfg(epochs=2)
    seeds = [member_seed(7, k) for k in range(3)]
    assert seeds[0] == 7 and len(set(seeds)) == 3 and min(seeds[1:]) >= 2 ** 32
    members = [train_models(data, cfg, s, tmp_path, 0.2, progress=False) for s in seeds[:2]]
    again = train_models(data, cfg, 7, tmp_path, 0.2, progress=False)
    assert again.cached and again.key == members[0].key
    both = ensemble(members)
    X = torch.from_numpy(design(data, DECOMPOSED[0], np.arange(20))[0])
    with torch.no_grad():
        np.testing.assert_allclose(both.nets["d"](X).numpy(),
                                   (members[0].nets["d"](X) + members[1].nets["d"](X)).numpy() / 2, rtol=1e-5)
    assert both.key not in (members[0].key, members[1].key) and ensemble(members[:1]) is members[0]
