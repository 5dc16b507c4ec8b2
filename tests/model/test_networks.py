"""The residual MLP and its training: shapes, no normalisation layers, learning, the cache."""
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from sdexp.config import ModelConfig
from sdexp.errors import UserError
from sdexp.model import training
from sdexp.model.dataset import Dataset
from sdexp.model.networks import ResidualMLP
from sdexp.model.specs import DECOMPOSED, UNDECOMPOSED
from sdexp.model.training import design, train_models


class SyntheticDataset(Dataset):
    """A Dataset whose split holds out whole episodes (the real one's documented behaviour)."""

    def split(self, validation_fraction, seed):
        ep = self.arrays["episode"]
        ids = np.unique(ep)
        rng = np.random.default_rng(seed)
        n_val = max(1, int(round(validation_fraction * len(ids))))
        val_ids = rng.choice(ids, n_val, replace=False)
        val = np.isin(ep, val_ids)
        return np.flatnonzero(~val), np.flatnonzero(val)


def synthetic_dataset(n=4000, n_s=3, n_e=3, dim=3, m=4, episode_len=200, seed=0, n_raw=None):
    """Random states with a learnable linear law for every next velocity:
    v_next = 0.9 v + 0.1 (u W) + 0.05 (other inputs) -- as in s_dot_next = 0.9 s_dot + 0.1 u."""
    rng = np.random.default_rng(seed)
    a = {k: rng.normal(size=(n, w)).astype(np.float32) for k, w in
         (("s", n_s), ("s_dot", n_s), ("e", n_e), ("e_dot", n_e), ("p", dim), ("p_dot", dim))}
    a["u"] = rng.uniform(-1, 1, (n, m)).astype(np.float32)
    for spec in DECOMPOSED:
        X, _, base = design({**a, spec.target: a[spec.current]}, spec)
        W = rng.normal(size=(X.shape[1], len(base))) * 0.05
        W[base, np.arange(len(base))] = 0.9
        a[spec.target] = (X @ W).astype(np.float32)
    n_raw = n_raw or (dim + 3 * n_s)
    a["raw"] = rng.normal(size=(n, n_raw)).astype(np.float32)
    a["raw_dot"] = rng.normal(size=(n, n_raw)).astype(np.float32)
    a["raw_dot_next"] = (0.9 * a["raw_dot"] + 0.1 * np.sin(3 * a["raw"])).astype(np.float32)
    a["episode"] = (np.arange(n) // episode_len).astype(np.int32)
    a["t"] = (0.01 * (np.arange(n) % episode_len)).astype(np.float32)
    return SyntheticDataset(a, {"n_s": n_s, "n_e": n_e, "dim": dim, "m": m, "control_dt": 0.01})


def model_cfg(**kw):
    base = dict(hidden=32, blocks=2, epochs=3, batch_size=128, lr=3e-3, lr_step=2, threads=1)
    base.update(kw)
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(ModelConfig), base))


def test_shapes_and_architecture():
    net = ResidualMLP(7, 3, hidden=16, blocks=4, base=[4, 5, 6])
    assert net(torch.randn(11, 7)).shape == (11, 3)
    assert net(torch.randn(7)).shape == (3,)
    assert len(net.blocks) == 4
    kinds = {type(m) for m in net.modules()}
    assert not any(issubclass(k, (nn.modules.batchnorm._NormBase, nn.LayerNorm, nn.GroupNorm)) for k in kinds)
    linears = [m for m in net.modules() if isinstance(m, nn.Linear)]
    assert len(linears) == 2 + 2 * 4 and all(l.out_features == 16 for l in linears[:-1])
    # one residual block is relu(h + fc2(relu(fc1(h))))
    blk, h = net.blocks[0], torch.randn(5, 16)
    ref = torch.relu(h + blk.fc2(torch.relu(blk.fc1(h))))
    assert torch.allclose(blk(h), ref)


def test_output_is_current_velocity_plus_destandardised_residual():
    net = ResidualMLP(4, 2, hidden=8, blocks=1, base=[2, 3])
    x, y = torch.randn(500, 4), torch.randn(500, 2)
    net.fit_scaling(x, y)
    xb = torch.randn(3, 4)
    expect = xb[:, 2:] + net.out_mean + net.out_std * net.raw_output(xb)
    assert torch.allclose(net(xb), expect)
    # the loss target inverts the output map
    assert torch.allclose(net.target_raw(xb, net(xb)), net.raw_output(xb), atol=1e-5)
    # the scaling lives in buffers: a state dict rebuilds the same function
    clone = ResidualMLP.from_saved(net.spec(), net.state_dict())
    assert torch.allclose(clone(xb), net(xb))
    # a constant input channel is shifted, never divided by ~0
    x[:, 0] = 1.5
    net.fit_scaling(x, y)
    assert net.in_std[0] == 1.0 and torch.isfinite(net(x)).all()


def test_training_learns_a_linear_system(tmp_path):
    data = synthetic_dataset(n=6000)
    cfg = model_cfg(epochs=6)
    res = train_models(data, cfg, seed=0, cache_dir=None, validation_fraction=0.2, progress=False)
    assert set(res.nets) == {"d", "g", "h"} and not res.cached
    for name, h in res.history.items():
        assert list(h["epoch"]) == list(range(1, 7))
        assert h["val_l1"].iloc[-1] < 0.35 * h["val_l1"].iloc[0] or h["val_l1"].iloc[-1] < 0.1, name
        assert h["train_loss"].iloc[-1] < h["train_loss"].iloc[0]
        assert res.seconds[name] > 0
    # StepLR: x0.8 every 2 epochs
    assert np.allclose(res.history["d"]["lr"], 3e-3 * 0.8 ** ((np.arange(1, 7) - 1) // 2))
    # and the learned d beats "no change" by far on held-out episodes
    assert res.history["d"]["val_rel_l1"].iloc[-1] < 0.25 < res.history["d"]["val_rel_l1"].iloc[0] + 0.5
    train_idx, val_idx = data.split(0.2, 0)
    X, Y, _ = design(data, DECOMPOSED[0], val_idx)
    with torch.no_grad():
        err = (res.nets["d"](torch.from_numpy(X)) - torch.from_numpy(Y)).abs().mean()
    assert err < 0.2 * np.abs(Y - X[:, 3:6]).mean()


def test_training_is_seeded():
    data = synthetic_dataset(n=1500)
    cfg = model_cfg(epochs=1)
    a = train_models(data, cfg, 3, None, 0.2, specs=DECOMPOSED[:1], progress=False)
    b = train_models(data, cfg, 3, None, 0.2, specs=DECOMPOSED[:1], progress=False)
    assert a.history["d"]["val_l1"].iloc[-1] == b.history["d"]["val_l1"].iloc[-1]


def test_cache_second_call_loads_without_training(tmp_path, monkeypatch):
    data = synthetic_dataset(n=1500)
    cfg = model_cfg(epochs=2)
    first = train_models(data, cfg, 0, tmp_path, 0.2, progress=False)
    files = list(tmp_path.glob("nets-*.pt"))
    assert len(files) == 1 and not list(tmp_path.glob(".*tmp"))

    def boom(*a, **k):
        raise AssertionError("trained again instead of loading")
    monkeypatch.setattr(training, "train_network", boom)
    second = train_models(data, cfg, 0, tmp_path, 0.2, progress=False)
    assert second.cached and second.key == first.key
    assert second.seconds == first.seconds
    x = torch.from_numpy(design(data, DECOMPOSED[2])[0][:5])
    assert torch.equal(second.nets["h"](x), first.nets["h"](x))
    # another seed, model config or dataset is another entry
    assert training.models_key(data, cfg, 1, 0.2, DECOMPOSED) != first.key
    assert training.models_key(data, model_cfg(epochs=3), 0, 0.2, DECOMPOSED) != first.key
    assert training.models_key(synthetic_dataset(n=1500, seed=1), cfg, 0, 0.2, DECOMPOSED) != first.key
    # an entry of another format version, or a damaged one, is retrained, never used
    monkeypatch.undo()
    blob = torch.load(files[0], weights_only=True)
    blob["version"] = -1
    torch.save(blob, files[0])
    assert not train_models(data, cfg, 0, tmp_path, 0.2, progress=False).cached
    files[0].write_bytes(b"garbage")
    assert not train_models(data, cfg, 0, tmp_path, 0.2, progress=False).cached
    assert train_models(data, cfg, 0, tmp_path, 0.2, progress=False).cached


def test_undecomposed_network_trains_on_raw_keys():
    data = synthetic_dataset(n=1500)
    res = train_models(data, model_cfg(epochs=1), 0, None, 0.2, specs=UNDECOMPOSED, progress=False)
    net = res.nets["raw"]
    n_raw = data.arrays["raw"].shape[1]
    assert (net.n_in, net.n_out) == (2 * n_raw + 4, n_raw)


def test_bad_input_is_a_clear_error():
    data = synthetic_dataset(n=1000, episode_len=100)
    with pytest.raises(UserError, match="model.batch_size"):
        train_models(data, model_cfg(batch_size=2048), 0, None, 0.2, progress=False)
    with pytest.raises(UserError, match="raw"):
        a = dict(data.arrays)
        del a["raw"]
        train_models(SyntheticDataset(a), model_cfg(), 0, None, 0.2, specs=UNDECOMPOSED, progress=False)
    with pytest.raises(UserError, match="model.loss"):
        train_models(data, model_cfg(epochs=1, loss="huber"), 0, None, 0.2, progress=False)


def test_drone_without_peripheral_sensors_has_no_d():
    data = synthetic_dataset(n=1000, n_s=0, episode_len=100)
    res = train_models(data, model_cfg(epochs=1), 0, None, 0.2, progress=False)
    assert res.skipped == ["d"] and set(res.nets) == {"g", "h"}


def test_parallel_training_gives_the_same_networks():
    """model.threads >= 2 trains the networks in one-thread worker processes: same result as
    one-thread training in this process."""
    data = synthetic_dataset(n=1200)
    seq = train_models(data, model_cfg(epochs=2, threads=1), 0, None, 0.2, progress=False)
    par = train_models(data, model_cfg(epochs=2, threads=2), 0, None, 0.2, progress=False)
    assert par.wall_seconds > 0 and set(par.nets) == {"d", "g", "h"}
    for name in seq.nets:
        np.testing.assert_allclose(par.history[name]["val_l1"], seq.history[name]["val_l1"], rtol=1e-6)
        x = torch.from_numpy(design(data, DECOMPOSED[2])[0][:4]) if name == "h" else None
        if x is not None:
            assert torch.allclose(par.nets["h"](x), seq.nets["h"](x), atol=1e-6)


def test_the_best_validation_epoch_is_kept_or_the_last():
    from dataclasses import replace

    data = synthetic_dataset(n=1500)
    train_idx, val_idx = data.split(0.2, 0)
    X_tr, Y_tr, base = design(data, DECOMPOSED[0], train_idx)
    X_va, Y_va, _ = design(data, DECOMPOSED[0], val_idx)
    cfg = model_cfg(epochs=6, lr=3e-2)   # a large step: the validation loss is not monotone
    assert cfg.keep_best is True   # the default
    for keep in (True, False):
        plain = replace(cfg, keep_best=keep)
        net, hist, _ = training.train_network(X_tr, Y_tr, X_va, Y_va, base, plain, 0, progress=False)
        chosen = hist[hist["selected"]]
        assert len(chosen) == 1
        expect = hist["val_loss"].idxmin() if keep else len(hist) - 1
        assert chosen.index[0] == expect
        with torch.no_grad():
            x, y = torch.from_numpy(X_va), torch.from_numpy(Y_va)
            loss = (net.raw_output(x) - net.target_raw(x, y)).abs().mean()
        assert float(loss) == pytest.approx(chosen["val_loss"].iloc[0], rel=1e-5)
    assert training.models_key(data, plain, 0, 0.2, DECOMPOSED) != training.models_key(data, cfg, 0, 0.2, DECOMPOSED)


def test_horizon_targets_stay_inside_one_hold_of_one_episode():
    """model.horizon = k: the target of row i is row i + k - 1's next velocity, and only rows
    whose k frames share the episode and the command are kept."""
    n = 12
    a = {"s": np.arange(n, dtype=np.float32)[:, None], "s_dot": np.zeros((n, 1), np.float32),
         "u": np.repeat(np.array([[0.0], [1.0], [2.0]], np.float32), [5, 4, 3], axis=0),
         "s_dot_next": 100 + np.arange(n, dtype=np.float32)[:, None],
         "episode": np.array([0] * 7 + [1] * 5, np.int32)}
    a["t"] = np.concatenate([0.01 * np.arange(7), 0.01 * np.arange(5)]).astype(np.float32)
    d = DECOMPOSED[0]
    X, Y, _ = design(a, d, horizon=3)
    # holds: rows 0-4 (u 0), 5-8 (u 1; episode 1 starts at 7), 9-11 (u 2)
    kept = X[:, 0].astype(int).tolist()   # input column 0 is s = the row number
    assert kept == [0, 1, 2, 9]
    np.testing.assert_array_equal(Y[:, 0], 100 + np.array(kept) + 2)
    X1, Y1, _ = design(a, d, horizon=1)
    assert len(X1) == n and np.array_equal(Y1[:, 0], a["s_dot_next"][:, 0])
    # the split's indices are honoured: only kept rows that are in idx
    X2, _, _ = design(a, d, idx=np.array([1, 2, 3, 10]), horizon=3)
    assert X2[:, 0].astype(int).tolist() == [1, 2]


def test_a_command_delay_pairs_each_row_with_the_command_sent_that_many_frames_before():
    """model.command_delay = d: row i's input u is row i - d's command (the thrust acting on it);
    the first d rows of every episode have none and are dropped; with a horizon as well, the
    k frames share the acting command."""
    n = 12
    a = {"s": np.arange(n, dtype=np.float32)[:, None], "s_dot": np.zeros((n, 1), np.float32),
         "u": np.arange(n, dtype=np.float32)[:, None] * 10,
         "s_dot_next": 100 + np.arange(n, dtype=np.float32)[:, None],
         "episode": np.array([0] * 7 + [1] * 5, np.int32)}
    d = DECOMPOSED[0]
    u_col = d.inputs.index("u")
    X, Y, _ = design(a, d, delay=2)
    rows = X[:, 0].astype(int)
    assert rows.tolist() == [2, 3, 4, 5, 6, 9, 10, 11]
    np.testing.assert_array_equal(X[:, u_col], (rows - 2) * 10)          # the command two frames back
    np.testing.assert_array_equal(Y[:, 0], 100 + rows)                  # the target is this row's
    a["u"] = np.repeat(np.array([[0.0], [1.0], [2.0]], np.float32), [5, 4, 3], axis=0)
    X, _, _ = design(a, d, horizon=2, delay=1)
    # acting commands (one frame late): rows 1-5 u 0, 6-9 u 1 (episode 1 starts at 7), 10-11 u 2
    assert X[:, 0].astype(int).tolist() == [1, 2, 3, 4, 8, 10]


def test_the_model_key_is_the_configs_key_fields():
    """Every field that trains other nets is in the key; the thread count is not."""
    data = synthetic_dataset(n=400, episode_len=100)
    k1 = training.models_key(data, model_cfg(), 0, 0.2, DECOMPOSED)
    assert k1 != training.models_key(data, model_cfg(horizon=3), 0, 0.2, DECOMPOSED)
    assert k1 != training.models_key(data, model_cfg(command_delay=3), 0, 0.2, DECOMPOSED)
    from sdexp.cache import config_key   # at its default the delay is not in the key: earlier nets keep theirs
    assert "command_delay" not in config_key(model_cfg()) and "command_delay" in config_key(model_cfg(command_delay=3))
    assert k1 == training.models_key(data, model_cfg(threads=2), 0, 0.2, DECOMPOSED)


def test_linear_nets_fit_a_linear_law_and_key_only_when_asked():
    """model.linear: those nets are one affine map (no hidden layer); on an exactly linear law
    they beat the MLPs' "no change" baseline as the MLPs do, and the key changes only when the
    list is not empty (the all-MLP nets keep theirs)."""
    data = synthetic_dataset(n=6000)
    res = train_models(data, model_cfg(epochs=6, linear=["d", "h"]), 0, None, 0.2, progress=False)
    assert res.nets["d"].inp is None and len(res.nets["d"].blocks) == 0
    assert res.nets["g"].inp is not None
    lin = [m for m in res.nets["h"].modules() if isinstance(m, nn.Linear)]
    assert len(lin) == 1 and lin[0].in_features == res.nets["h"].n_in
    for name in ("d", "h"):
        assert res.history[name]["val_rel_l1"].iloc[-1] < 0.25, name
    clone = ResidualMLP.from_saved(res.nets["d"].spec(), res.nets["d"].state_dict())
    x = torch.randn(5, res.nets["d"].n_in)
    assert torch.allclose(clone(x), res.nets["d"](x))
    base = training.models_key(data, model_cfg(), 0, 0.2, DECOMPOSED)
    assert base == training.models_key(data, model_cfg(linear=[]), 0, 0.2, DECOMPOSED)
    assert training.models_key(data, model_cfg(linear=["h", "d"]), 0, 0.2, DECOMPOSED) == \
        training.models_key(data, model_cfg(linear=["d", "h"]), 0, 0.2, DECOMPOSED) != base


def test_a_prior_is_added_to_the_current_velocity_and_the_net_learns_the_rest():
    """model.prior: the prior's change (per newton of the command, the inputs' last m columns,
    and a constant, over alpha) is part of what the residual is added to; the nets of g and h
    get it, d none; saved and loaded with it; keyed only with one."""
    data = synthetic_dataset(n=2000)
    m, alpha = 4, 0.01
    per_newton = np.arange(12.0).reshape(3, m)
    priors = {"p_dot_next": (per_newton, np.array([0.0, -9.81, 0.0])), "e_dot_next": (np.ones((3, m)), np.zeros(3))}
    res = train_models(data, model_cfg(epochs=1), seed=0, cache_dir=None, validation_fraction=0.2,
                       progress=False, priors=priors)
    h, d = res.nets["h"], res.nets["d"]
    assert h.has_prior and res.nets["g"].has_prior and not d.has_prior
    np.testing.assert_allclose(h.prior_W[:, -m:].numpy(), alpha * per_newton, rtol=1e-6)
    assert not h.prior_W[:, :-m].any() and np.isclose(float(h.prior_b[1]), -9.81 * alpha)
    X, Y, base = design(data, DECOMPOSED[2])
    x = torch.from_numpy(X[:5])
    with torch.no_grad():
        current = x[:, base] + x[:, -m:] @ torch.from_numpy(alpha * per_newton.T).float() + h.prior_b
        np.testing.assert_allclose(h.current(x).numpy(), current.numpy(), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(h(x).numpy(), (current + h.out_mean + h.out_std * h.raw_output(x)).numpy(),
                                   rtol=1e-5, atol=1e-6)
    again = ResidualMLP.from_saved(h.spec(), h.state_dict())
    assert again.has_prior and torch.equal(again.prior_W, h.prior_W)
    keys = {training.models_key(data, model_cfg(), 0, 0.2, DECOMPOSED, p) for p in (None, priors)}
    assert len(keys) == 2 and training.models_key(data, model_cfg(), 0, 0.2, DECOMPOSED) in keys
