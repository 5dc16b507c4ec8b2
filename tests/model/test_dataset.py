"""Training data: layout, the paper's thrust holds, determinism across workers, the cache
(hit, resume after a kill, stale entries), the split by episodes and physical consistency."""
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sdexp.errors import UserError
from sdexp.model import generate
from sdexp.model.dataset import KEYS, DATA_FORMAT, Dataset, _write_npz, dataset_key, dataset_spec, load_dataset
from tests.conftest import make_config

CHUNK = 200          # three chunks of the 600 transitions below
SMALL = ["drone=rod", "data=paper", "data.samples=600", "data.hold_seconds=0.5", "data.episode_seconds=1.5",
         "data.workers=1", "model.batch_size=64"]


def small_config(cache_dir, *overrides):
    """The typed config of the small data set above, caching in ``cache_dir``."""
    return make_config(*SMALL, f"cache_dir={cache_dir}", *overrides)


def final_path(cfg) -> Path:
    spec = dataset_spec(cfg, CHUNK)
    return Path(spec["cache_dir"]) / f"{dataset_key(spec)}.npz"


def assert_same(a: Dataset, b: Dataset):
    assert set(a.arrays) == set(b.arrays) == set(KEYS)
    for k in KEYS:
        np.testing.assert_array_equal(a.arrays[k], b.arrays[k], err_msg=k)


@pytest.fixture(scope="module")
def reference(cache_dir):
    cfg = small_config(cache_dir)
    return cfg, load_dataset(cfg, CHUNK)


def episodes(ds):
    ep = ds.arrays["episode"]
    return [np.flatnonzero(ep == e) for e in np.unique(ep)]


def test_keys_shapes_and_meta(reference):
    cfg, ds = reference
    a, n = ds.arrays, 600
    assert len(ds) == n and tuple(a) == KEYS
    n_s, m, dim = 8, 5, 2
    widths = {"s": n_s, "s_dot": n_s, "s_dot_next": n_s, "e": 1, "e_dot": 1, "e_dot_next": 1,
              "p": dim, "p_dot": dim, "p_dot_next": dim, "u": m, "raw": dim + 1 + n_s,
              "raw_dot": dim + 1 + n_s, "raw_dot_next": dim + 1 + n_s}
    for k, w in widths.items():
        assert a[k].shape == (n, w) and a[k].dtype == np.float32, k
        assert np.all(np.isfinite(a[k])), k
    assert a["episode"].shape == (n,) and a["episode"].dtype == np.int32
    assert a["t"].shape == (n,) and a["t"].dtype == np.float32
    mt = ds.meta
    assert (mt["drone"], mt["dim"], mt["n_s"], mt["n_e"], mt["m"]) == ("rod", 2, 8, 1, 5)
    assert mt["control_dt"] == 0.01 and mt["max_thrust"] == 10.0 and mt["format"] == DATA_FORMAT
    assert mt["episodes"] == len(np.unique(a["episode"])) >= 4     # 1.5 s episodes, 6 s of data
    assert sum(mt["ends"].values()) >= mt["episodes"] - 1
    assert set(mt["failures"]) == {"inverted_element", "non_finite", "runaway_speed", "runaway_extent"}
    assert mt["samples_per_second"] > 0 and mt["wall_seconds"] > 0


def test_thrusts_are_uniform_holds_within_the_limit(reference):
    _, ds = reference
    u, t = ds.arrays["u"], ds.arrays["t"]
    assert np.all(np.abs(u) <= 10.0) and u.min() < -5 and u.max() > 5
    hold = 50                                               # 0.5 s at 100 Hz
    for idx in episodes(ds):
        k = np.rint(t[idx] / 0.01).astype(int)
        np.testing.assert_array_equal(k, np.arange(len(idx)))  # every episode starts at rest, t = 0
        block = k // hold
        for b in np.unique(block):
            rows = u[idx[block == b]]
            assert np.all(rows == rows[0])                  # constant over the hold ...
        if block.max() > 0:
            assert np.all(u[idx[k == hold]] != u[idx[0]])   # ... redrawn after it


def test_rates_are_consistent_with_the_states_without_noise(cache_dir):
    # gentle thrusts (3 N a rotor): at full thrust the 8 m rod whips faster than 100 Hz resolves
    ds = load_dataset(small_config(cache_dir, "noise=none", "drone.max_thrust=3"), CHUNK)
    a, dt = ds.arrays, 0.01
    pairs = np.concatenate([idx[:-1] for idx in episodes(ds)])  # k and k + 1 in one episode
    nxt = pairs + 1
    # the next state's rates are the same readings as this transition's *_next
    for key in ("s_dot", "e_dot", "p_dot", "raw_dot"):
        np.testing.assert_array_equal(a[f"{key}_next"][pairs], a[key][nxt])
    # finite differences of the read state agree with the mean of the read rates
    for key in ("p", "s", "e", "raw"):
        step = a[key][nxt].astype(float) - a[key][pairs]
        fd = (step if key == "p" else np.angle(np.exp(1j * step))) / dt   # angles: mod 2 pi
        mid = 0.5 * (a[f"{key}_dot"][pairs] + a[f"{key}_dot_next"][pairs])
        scale = np.abs(mid).max()
        assert scale > 1.0, key                                           # it does move
        assert np.median(np.abs(fd - mid)) < 0.02 * scale, key
        # what 100 Hz does not resolve of the rod's fast bending modes: the worst channel correlates
        # 0.992-0.993 over seeds 0-3 with the thrust shared equally among a patch's vertices, and
        # 0.985-0.988 with it as a traction over the disc (since 2026-11-26: concentrated under the
        # anchor, it excites the higher modes more; the same at 2 N)
        for j in range(fd.shape[1]):
            assert np.corrcoef(fd[:, j], mid[:, j])[0, 1] > 0.98, (key, j)
    # the undecomposed state holds p and e first; its 2D rates are the gyroscope readings
    np.testing.assert_array_equal(a["raw"][:, :3], np.c_[a["p"], a["e"]])
    np.testing.assert_array_equal(a["raw_dot"][:, :3], np.c_[a["p_dot"], a["e_dot"]])


def test_same_data_for_one_and_two_workers_and_other_data_for_another_seed(reference, tmp_path):
    cfg, ds1 = reference
    ds2 = load_dataset(small_config(tmp_path / "two", "data.workers=2"), CHUNK)
    assert ds2.meta["workers"] == 2 and not ds2.meta["cached"]
    assert_same(ds1, ds2)
    other = load_dataset(small_config(tmp_path / "seed", "seed=1"), CHUNK)
    assert not np.array_equal(other.arrays["u"], ds1.arrays["u"])


def test_second_load_is_a_fast_equal_cache_hit(reference):
    cfg, ds = reference
    t0 = time.perf_counter()
    again = load_dataset(cfg, CHUNK)
    assert time.perf_counter() - t0 < 2.0
    assert again.meta["cached"] and not ds.meta["cached"]
    assert_same(ds, again)
    assert final_path(cfg).exists() and not final_path(cfg).with_suffix(".chunks").exists()


def test_a_killed_generation_resumes_from_its_chunks(reference, tmp_path, monkeypatch):
    _, ds = reference
    cfg = small_config(tmp_path)
    real = generate.generate_chunk
    made = []

    def dies_in_chunk_2(spec, chunk, n, progress=None):
        if chunk == 2:
            raise KeyboardInterrupt  # as if killed while simulating the third chunk
        made.append(chunk)
        return real(spec, chunk, n, progress)

    monkeypatch.setattr(generate, "generate_chunk", dies_in_chunk_2)
    with pytest.raises(KeyboardInterrupt):
        load_dataset(cfg, CHUNK)
    folder = final_path(cfg).with_suffix(".chunks")
    assert sorted(p.name for p in folder.glob("*.npz")) == ["chunk-00000.npz", "chunk-00001.npz"]
    assert not final_path(cfg).exists()
    (folder / ".chunk-00002.npz.half.tmp").write_bytes(b"half-written")  # a killed write

    monkeypatch.setattr(generate, "generate_chunk", real)
    resumed = load_dataset(cfg, CHUNK)
    assert made == [0, 1] and resumed.meta["chunks_resumed"] == 2
    assert_same(ds, resumed)
    assert not folder.exists()


def test_a_stale_or_corrupt_cache_entry_is_regenerated_not_read(reference, tmp_path, caplog):
    _, ds = reference
    cfg = small_config(tmp_path)
    path = final_path(cfg)
    bad = {k: v[:10] for k, v in ds.arrays.items()}
    _write_npz(path, bad, {**ds.meta, "format": DATA_FORMAT + 1, "samples": 10})   # other version
    caplog.clear()
    assert_same(ds, load_dataset(cfg, CHUNK))
    assert "unusable" in caplog.text and "format" in caplog.text   # a logged warning
    arrays = dict(ds.arrays)
    del arrays["raw"]
    _write_npz(path, arrays, ds.meta)                                              # a key missing
    caplog.clear()
    assert_same(ds, load_dataset(cfg, CHUNK))
    assert "unusable" in caplog.text and "missing" in caplog.text   # a logged warning
    path.write_bytes(b"not a zip file")                                            # corrupt
    caplog.clear()
    assert_same(ds, load_dataset(cfg, CHUNK))
    assert "unusable" in caplog.text and "unreadable" in caplog.text   # a logged warning


def test_split_keeps_every_episode_on_one_side(reference):
    _, ds = reference
    train, val = ds.split(0.25, seed=3)
    assert len(train) + len(val) == len(ds) and len(np.intersect1d(train, val)) == 0
    ep = ds.arrays["episode"]
    assert len(np.intersect1d(ep[train], ep[val])) == 0
    assert 0 < len(val) < len(ds) / 2
    np.testing.assert_array_equal(ds.split(0.25, seed=3)[1], val)      # seeded


def test_too_small_a_dataset_or_no_sensors_is_a_clear_error(cache_dir):
    with pytest.raises(UserError, match=r"data\.samples.*model\.batch_size"):
        load_dataset(small_config(cache_dir, "data.samples=100", "model.batch_size=512"), CHUNK)
    with pytest.raises(UserError, match=r"drone\.num_sensors = 0"):
        load_dataset(small_config(cache_dir, "drone.num_sensors=0"), CHUNK)
    # enough transitions by count, but one episode cannot be split into train and validation
    with pytest.raises(UserError, match=r"data\.samples"):
        load_dataset(small_config(cache_dir, "data.samples=100", "model.batch_size=32",
                              "data.episode_seconds=30"), CHUNK)


def test_raw_3d_state_rates_are_the_derivative_of_the_raw_state():
    """3D: the peripheral IMUs' world Euler angles and their chain-rule rates, on readings of
    IMUs spinning at constant angular velocity (central differences as the reference)."""
    from sdexp.model.generate import raw_state
    from sdexp.sensing.rotations import euler_from_matrix, euler_rates, exp_so3
    from sdexp.sensing import Readings, SensorLayout, decompose

    rng = np.random.default_rng(0)
    k = 5                                            # IMU 0 is the frame, 1..4 peripheral
    r_hat = np.array([[1.0, 0, 0], [0, 0, 1], [-1, 0, 0], [0, 0, -1]])
    layout = SensorLayout(3, np.array([0]), np.arange(1, k), r_hat)
    R0 = exp_so3(rng.normal(0, 0.4, (k, 3)))
    w = rng.normal(0, 1.0, (k, 3))
    pos0, vel = rng.normal(0, 1, (k, 3)), rng.normal(0, 1, (k, 3))

    def raw_at(t):
        r = Readings(t, pos0 + vel * t, vel, exp_so3(w * t) @ R0, w)
        return raw_state(r, decompose(r, layout), layout)

    raw, raw_dot = raw_at(0.3)
    assert raw.shape == raw_dot.shape == (3 + 3 + 4 * 3,)
    R = exp_so3(w * 0.3) @ R0                         # the convention of sdexp.sensing.rotations
    np.testing.assert_allclose(raw[6:], euler_from_matrix(R[1:]).ravel(), atol=1e-12)
    np.testing.assert_allclose(raw_dot[6:], euler_rates(euler_from_matrix(R[1:]), w[1:]).ravel(), atol=1e-9)
    h = 1e-6
    fd = (raw_at(0.3 + h)[0] - raw_at(0.3 - h)[0]) / (2 * h)
    np.testing.assert_allclose(raw_dot, fd, rtol=1e-5, atol=1e-5)


def test_thrust_range_narrows_the_holds_and_keys_the_cache(tmp_path):
    narrow = small_config(str(tmp_path), "data=paper", "data.samples=400", "data.thrust_range=[0.0,0.2]")
    u = load_dataset(narrow, CHUNK).arrays["u"]
    assert u.min() >= 0.0 and u.max() <= 2.0 + 1e-6 and u.max() > 1.0
    explicit = small_config(str(tmp_path), "data=paper", "data.thrust_range=[-1.0,1.0]")
    paper = small_config(str(tmp_path), "data=paper")
    assert dataset_key(dataset_spec(explicit, CHUNK)) == dataset_key(dataset_spec(paper, CHUNK))
    wide = small_config(str(tmp_path), "data=paper", "data.samples=400")
    assert dataset_key(dataset_spec(narrow, CHUNK)) != dataset_key(dataset_spec(wide, CHUNK))


def test_around_hover_centres_the_holds_on_the_hover_thrust(tmp_path):
    from sdexp.sim.drone import build_drone
    from sdexp.sim.rigid.geometry import rest_hover_thrust

    cfg = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.05,0.05]")
    assert cfg.data.around_hover
    u = load_dataset(cfg, CHUNK).arrays["u"]
    hover = rest_hover_thrust(build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element), float(cfg.sim.gravity))
    tmax = float(cfg.drone.max_thrust)
    assert np.all(np.abs(u - hover) <= 0.05 * tmax + 1e-5)
    assert np.abs(u - hover).max() > 0.03 * tmax            # the draws span the range
    # hover thrust carries the weight: summed vertical share about m g for this level rod
    assert hover.sum() == pytest.approx(float(cfg.drone.mass) * float(cfg.sim.gravity), rel=0.05)
    off = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.05,0.05]",
                   "data.around_hover=false")
    assert dataset_key(dataset_spec(off, CHUNK)) != dataset_key(dataset_spec(cfg, CHUNK))
    rigid = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.05,0.05]",
                     "data.hover=rigid")
    assert dataset_key(dataset_spec(rigid, CHUNK)) == dataset_key(dataset_spec(cfg, CHUNK))


def test_shape_hover_centres_the_holds_on_the_shape_holding_thrust(tmp_path, monkeypatch):
    from sdexp.sim.drone import build_drone
    from sdexp.sim.rigid.statics import shape_hover_thrust

    cfg = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.01,0.01]",
                   "data.hover=shape")
    u = load_dataset(cfg, CHUNK).arrays["u"]
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    shape = shape_hover_thrust(drone, cfg.sim)
    assert np.all(np.abs(u - shape) <= 0.01 * float(cfg.drone.max_thrust) + 1e-5)
    # the data found it once; with the cache it is read (bit for bit), not held again
    from sdexp.sim.rigid import statics
    monkeypatch.setattr(statics, "_shape_hover_thrust", lambda *a: pytest.fail("found again, not read"))
    np.testing.assert_array_equal(shape_hover_thrust(drone, cfg.sim, cache_dir=cfg.cache_dir), shape)
    heavier = replace(cfg.sim, gravity=1.5 * float(cfg.sim.gravity))   # another world is never read from it
    with pytest.raises(pytest.fail.Exception, match="found again"):
        shape_hover_thrust(drone, heavier, cache_dir=cfg.cache_dir)
    rigid = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.01,0.01]")
    assert dataset_key(dataset_spec(rigid, CHUNK)) != dataset_key(dataset_spec(cfg, CHUNK))


def test_bend_budget_narrows_each_rotor_to_what_bends_the_body_that_much(tmp_path):
    from sdexp.sim.drone import build_drone
    from sdexp.sim.rigid.statics import rotor_compliance

    over = ["data=near_hover", "data.samples=400", "data.thrust_range=[-0.3,0.3]"]
    cfg = small_config(str(tmp_path), *over, "data.bend_budget_deg=5")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    centre, scale = generate.thrust_draw(drone, cfg.data, cfg.sim)
    reach = 0.3 * float(cfg.drone.max_thrust)
    compliance = rotor_compliance(drone, cfg.sim, centre)
    # the budget binds on the soft rotors and only there: scale x reach x compliance = 5 deg, else scale 1
    assert np.all(scale <= 1.0) and scale.min() < 0.5
    np.testing.assert_allclose(np.where(scale < 1, np.degrees(scale * reach * compliance), 5.0), 5.0, rtol=1e-9)
    assert np.all(np.degrees(reach * compliance[scale == 1]) <= 5.0)
    u = load_dataset(cfg, CHUNK).arrays["u"]
    assert np.all(np.abs(u - centre) <= scale * reach + 1e-5)
    assert np.all(np.abs(u - centre).max(axis=0) > 0.3 * scale * reach)   # each rotor spans its own range (8 draws)
    free = small_config(str(tmp_path), *over)
    assert free.data.bend_budget_deg is None and generate.thrust_draw(drone, free.data, free.sim)[1] == 1.0
    assert dataset_key(dataset_spec(free, CHUNK)) != dataset_key(dataset_spec(cfg, CHUNK))


def test_obstacles_are_scenery_not_part_of_the_data(reference):
    cfg, _ = reference
    boxed = small_config(cfg.cache_dir, "sim.obstacles=[{min:[3,-6],max:[4,6]}]")
    assert dataset_key(dataset_spec(boxed, CHUNK)) == dataset_key(dataset_spec(cfg, CHUNK))
    assert dataset_spec(boxed, CHUNK)["sim"].obstacles == []


def test_deform_range_holds_patterns_with_no_net_lift_or_torque(tmp_path, monkeypatch):
    from sdexp.sim.drone import build_drone
    from sdexp.sim.rigid.geometry import deformation_patterns, rest_hover_thrust, rigid_body, wrench_matrix

    cfg = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.001,0.001]",
                   "data.deform_range=0.3", "data.deform_hold_seconds=0.5")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    fem = drone.fem
    _, _, _, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    W = wrench_matrix(pos, dirs)[[1, 2]]   # 2D: lift and the (tilting) torque
    null = deformation_patterns(drone)
    assert null.shape == (drone.num_rotors, drone.num_rotors - np.linalg.matrix_rank(W))
    np.testing.assert_allclose(null.T @ null, np.eye(null.shape[1]), atol=1e-12)
    np.testing.assert_allclose(W @ null, 0.0, atol=1e-9)

    ds = load_dataset(cfg, CHUNK).arrays
    offset = ds["u"] - rest_hover_thrust(drone, float(cfg.sim.gravity))
    tmax, dither = float(cfg.drone.max_thrust), 0.001 * float(cfg.drone.max_thrust)
    # the held pattern puts no net lift or torque on the rest shape (up to the fast dither)
    assert np.abs(offset @ W.T).max() <= np.abs(W).sum(axis=1).max() * dither + 1e-4
    assert np.abs(offset).max() <= 0.3 * tmax + dither + 1e-5
    assert np.abs(offset).max() > 0.15 * tmax                  # the draws span the range
    # held for 0.5 s: within each 50-step window from an episode's start the pattern changes by the dither only
    t = np.round(ds["t"] / 0.01).astype(int)
    for w in np.unique(ds["episode"] * 1000 + t // 50):
        rows = offset[ds["episode"] * 1000 + t // 50 == w]
        assert np.ptp(rows, axis=0).max() <= 2 * dither + 1e-5
    off = small_config(str(tmp_path), "data=near_hover", "data.samples=400", "data.thrust_range=[-0.001,0.001]")
    assert dataset_key(dataset_spec(off, CHUNK)) != dataset_key(dataset_spec(cfg, CHUNK))

    # a drone whose rotors cannot deform it without net lift or torque: a clear error
    monkeypatch.setattr(generate, "deformation_patterns", lambda d: np.zeros((d.num_rotors, 0)))
    with pytest.raises(UserError, match="data.deform_range"):
        generate.generate_chunk(dataset_spec(cfg, CHUNK), 0, 10)


def test_the_data_key_is_the_configs_key_fields(tmp_path):
    """A mirrored mesh is another body and gets another key; thread and worker counts are not
    part of it (sdexp.config.NOT_KEY), nor is the split."""
    cfg = small_config(str(tmp_path), "drone=star", "drone.mesh.mirror=[]")
    spec = dataset_spec(cfg, CHUNK)
    for other in ("sim.threads=2", "data.workers=3", "data.validation_fraction=0.3"):
        assert dataset_key(dataset_spec(small_config(str(tmp_path), "drone=star", "drone.mesh.mirror=[]", other),
                                        CHUNK)) == dataset_key(spec), other
    mirrored = dataset_spec(small_config(str(tmp_path), "drone=star", "drone.mesh.mirror=[x,z]"), CHUNK)
    assert dataset_key(mirrored) != dataset_key(spec)


def test_data_made_on_the_reduced_model_are_keyed_by_the_model_they_were_made_on(tmp_path):
    """data.sim_model puts the data on another simulator than the flights': the data's sim config
    carries it, so they are the same data as a run wholly on that model, and other data than
    the full model's; a wrong name lists the choices as the user writes them."""
    from sdexp.config import validate
    base = small_config(str(tmp_path), "drone=star")
    on_reduced = small_config(str(tmp_path), "drone=star", "data.sim_model=reduced")
    assert dataset_spec(on_reduced, CHUNK)["sim"].model == "reduced" and on_reduced.sim.model == "full"
    assert dataset_key(dataset_spec(on_reduced, CHUNK)) == dataset_key(
        dataset_spec(small_config(str(tmp_path), "drone=star", "sim.model=reduced"), CHUNK))
    assert dataset_key(dataset_spec(on_reduced, CHUNK)) != dataset_key(dataset_spec(base, CHUNK))
    assert dataset_key(dataset_spec(small_config(str(tmp_path), "drone=star", "data.sim_model=full"), CHUNK)) \
        == dataset_key(dataset_spec(base, CHUNK))
    with pytest.raises(UserError, match=r"data.sim_model = 'reduce'.*null, full or reduced"):
        validate(small_config(str(tmp_path), "drone=star", "data.sim_model=reduce"))
    with pytest.raises(UserError, match=r"data.sim_model = 'reduced'.*while sim.ground is set"):
        validate(small_config(str(tmp_path), "drone=star", "data.sim_model=reduced", "sim.ground=-1.0"))
