"""model.frame = heading: the learned model cannot depend on which way the drone faces (a turn
about +Y changes the yaw and the world-frame horizontal vectors, nothing else), its Jacobians
are the derivatives of what it computes, and the trainer builds the same rows from a turned flight."""
import numpy as np
import pytest
import torch

from sdexp.model.dynamics import LearnedDynamics
from sdexp.model.heading import applies, turn
from sdexp.model.networks import ResidualMLP
from sdexp.model.specs import DECOMPOSED
from sdexp.model.training import design
from tests.model.test_networks import synthetic_dataset

N_S, N_E, DIM, M = 4, 3, 3, 5


def nets(frame: str, seed: int = 0) -> dict:
    """Untrained d, g, h as wide as ``frame`` makes their inputs (the tilt: two angles)."""
    torch.manual_seed(seed)
    sizes = {"s": N_S, "s_dot": N_S, "e": 2 if frame == "heading" else N_E, "e_dot": N_E, "p_dot": DIM, "u": M}
    out = {}
    for spec in DECOMPOSED:
        n_in = sum(sizes[k] for k in spec.inputs)
        off = sum(sizes[k] for k in spec.inputs[: spec.inputs.index(spec.current)])
        width = sizes[spec.current]
        net = ResidualMLP(n_in, width, 32, 2, list(range(off, off + width)))
        with torch.no_grad():
            net.out_std.uniform_(0.05, 0.3)
        out[spec.name] = net.eval()
    return out


def dynamics(frame: str) -> LearnedDynamics:
    return LearnedDynamics(nets(frame), N_S, N_E, DIM, M, 0.01, frame=frame)


def turned_state(dyn: LearnedDynamics, x: np.ndarray, angle: float) -> np.ndarray:
    """x with the whole flight turned by ``angle`` about +Y."""
    sl, y = dyn.slices, x.copy()
    y[sl["e"].start + 1] += angle
    y[sl["p"]] = turn(x[sl["p"]], angle)
    y[sl["p_dot"]] = turn(x[sl["p_dot"]], angle)
    return y


def turned_rate(dyn: LearnedDynamics, f: np.ndarray, angle: float) -> np.ndarray:
    sl, g = dyn.slices, f.copy()
    for k in ("p", "p_dot"):
        g[sl[k]] = turn(f[sl[k]], angle)
    return g


@pytest.mark.parametrize("frame", ["heading", "world"])
def test_a_turned_flight_is_the_same_flight_turned(frame):
    dyn = dynamics(frame)
    rng = np.random.default_rng(3)
    x, u = rng.normal(size=dyn.n), rng.uniform(-1, 1, M)
    for angle in (0.4, -2.0, 3.0):
        moved = np.abs(dyn.f(turned_state(dyn, x, angle), u) - turned_rate(dyn, dyn.f(x, u), angle)).max()
        if frame == "heading":
            assert moved < 1e-12
        else:   # the paper's nets read the yaw: nothing stops them from depending on it
            assert moved > 1e-3


def test_heading_jacobians_match_central_differences():
    dyn = dynamics("heading")
    rng = np.random.default_rng(5)
    for _ in range(3):
        x, u = rng.normal(size=dyn.n), rng.uniform(-1, 1, M)
        f0, A, B = dyn.linearize(x, u)
        np.testing.assert_allclose(f0, dyn.f(x, u), rtol=1e-12, atol=1e-10)
        h = 1e-6
        Af = np.stack([(dyn.f(x + h * e, u) - dyn.f(x - h * e, u)) / (2 * h) for e in np.eye(dyn.n)], axis=1)
        Bf = np.stack([(dyn.f(x, u + h * e) - dyn.f(x, u - h * e)) / (2 * h) for e in np.eye(M)], axis=1)
        np.testing.assert_allclose(A, Af, atol=1e-6 * np.abs(A).max())
        np.testing.assert_allclose(B, Bf, atol=1e-6 * np.abs(B).max())
        yaw = dyn.slices["e"].start + 1
        assert not A[dyn.slices["e_dot"], yaw].any() and not A[dyn.slices["s_dot"], yaw].any()


def test_the_trainer_sees_a_turned_flight_as_the_same_flight():
    data = synthetic_dataset(n=600, n_s=N_S, n_e=N_E, dim=DIM, m=M).arrays
    angle = np.float32(1.1)
    turned = dict(data)
    turned["e"] = data["e"].copy()
    turned["e"][:, 1] += angle
    for k in ("p", "p_dot", "p_dot_next"):
        turned[k] = turn(data[k], angle).astype(np.float32)
    for spec in DECOMPOSED:
        X, Y, base = design(data, spec, frame="heading")
        X2, Y2, base2 = design(turned, spec, frame="heading")
        np.testing.assert_allclose(X2, X, atol=1e-5)
        np.testing.assert_allclose(Y2, Y, atol=1e-5)
        assert base2 == base and X.shape[1] == design(data, spec)[0].shape[1] - ("e" in spec.inputs)


def test_a_2d_drone_has_no_heading():
    assert applies("heading", 3) and not applies("heading", 1) and not applies("world", 3)
    with pytest.raises(ValueError, match="heading"):
        applies("body", 3)


def test_nets_trained_in_the_heading_frame_fly_in_it(tmp_path):
    """model.frame reaches the trainer (its own cache entry) and the model built from it."""
    from sdexp.model.training import train_models
    from tests.model.test_networks import model_cfg
    data = synthetic_dataset(n=1200, n_s=N_S, n_e=N_E, dim=DIM, m=M)
    world = train_models(data, model_cfg(), 0, tmp_path, 0.2, progress=False)
    heading = train_models(data, model_cfg(frame="heading"), 0, tmp_path, 0.2, progress=False)
    assert heading.key != world.key and heading.nets["g"].n_in == world.nets["g"].n_in - 1
    dyn = LearnedDynamics.from_trained(heading, data, 0.01, frame="heading")
    x, u = np.random.default_rng(0).normal(size=dyn.n), np.zeros(M)
    moved = dyn.f(turned_state(dyn, x, 0.7), u) - turned_rate(dyn, dyn.f(x, u), 0.7)
    assert np.abs(moved).max() < 1e-9
    with pytest.raises(ValueError, match="network"):   # nets of one frame read as the other's
        LearnedDynamics.from_trained(heading, data, 0.01)
