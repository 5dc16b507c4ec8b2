"""The bench's outside-the-library effects run through the plugin protocol, change the flight,
and the scenario list holds every kind."""
import numpy as np
import pytest

from sdexp.discrepancy import bench_effects
from sdexp.discrepancy.bench import scenarios
from sdexp.sim.simulator import Simulator


def fly(cfg, drone, effects, steps=60):
    from sdexp.config import NoiseConfig
    sim = Simulator(drone, cfg.sim, NoiseConfig(enabled=False), seed=1, effects=effects)
    hover = drone.fem.mass.sum() * 9.81 / drone.num_rotors
    for _ in range(steps):
        sim.step(hover * (1.3 + 0.1 * np.arange(drone.num_rotors)))   # unequal: crosstalk shows
    assert sim.alive
    return sim.state(noisy=False)


def test_each_outside_effect_runs_and_changes_the_flight(small_cfg, leaf):
    rng = np.random.default_rng(0)
    entries = [e for _, _, e in bench_effects.variants(leaf, rng)] + [e for _, e in bench_effects.unmodelled(leaf, rng)]
    nominal = fly(small_cfg, leaf, [])
    for e in entries:
        st = fly(small_cfg, leaf, [e])
        moved = np.abs(np.r_[st.p - nominal.p, st.e - nominal.e, st.p_dot - nominal.p_dot]).max()
        assert np.all(np.isfinite(st.x)) and moved > 1e-4, e


def test_the_hanging_weight_pulls_its_weight_at_rest(small_cfg, leaf):
    from sdexp.config import NoiseConfig
    sim = Simulator(leaf, small_cfg.sim, NoiseConfig(enabled=False), effects=[
        {"_target_": bench_effects.PATH + "HangingMass", "mass": 0.3, "damping": 2.0}])
    w = sim.effects[0]
    f = np.zeros_like(sim.x)
    w.body_forces(sim, f)
    assert f.sum(axis=0)[1] == pytest.approx(-0.3 * 9.81, rel=0.02)


def test_the_bench_lists_variants_and_unmodelled_kinds(leaf):
    scs = scenarios(leaf, ["wind"], 1, 1, False, 1, levels=(1,), variants=1)
    kinds = [s["kind"] for s in scs]
    assert kinds.count("variant") == 6 and kinds.count("unmodelled") == 5
    assert {s["truth"][0] for s in scs if s["kind"] == "variant"} == {"wind", "motor_lag", "payload"}
    assert len({s["seed"] for s in scs}) == len(scs)


def test_a_subset_of_the_bench_keeps_its_draws_and_unknown_ids_are_listed(leaf):
    from sdexp.discrepancy.bench import select
    from sdexp.errors import UserError
    scs = scenarios(leaf, ["wind", "payload"], 1, 2, False, 0, levels=(1,), variants=1)
    sub = select(scs, ["gusty_wind-a-0", "payload-b0"])
    assert [s["id"] for s in sub] == ["payload-b0", "gusty_wind-a-0"]
    assert sub == [s for s in scs if s["id"] in ("payload-b0", "gusty_wind-a-0")]   # the same draws and seeds
    assert select(scs, None) == scs
    with pytest.raises(UserError, match=r"unknown scenario\(s\) \['payload-a0'\]; this bench's are \['wind-b0'"):
        select(scs, ["payload-a0"])
