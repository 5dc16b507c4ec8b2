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


@pytest.mark.parametrize("entry, words", [
    ({"_target_": bench_effects.PATH + "RotorTilt", "angle": 2.0}, "rotor_tilt.angle = 2.0 is out of range: allowed in [-1.5, 1.5] rad"),
    ({"_target_": bench_effects.PATH + "PerRotorLag", "taus": [0.1, -0.05]}, "per_rotor_lag.taus = [0.1, -0.05] is out of range: allowed >= 0 s each"),
    ({"_target_": bench_effects.PATH + "PerRotorLag", "taus": []}, "per_rotor_lag.taus = [] is out of range: allowed one or more"),
    ({"_target_": bench_effects.PATH + "HangingMass", "mass": 0.0}, "hanging_mass.mass = 0.0 is out of range: allowed > 0 kg"),
    ({"_target_": bench_effects.PATH + "HangingMass", "stiffness": float("nan")}, "hanging_mass.stiffness = nan is out of range: allowed > 0 N/m"),
    ({"_target_": bench_effects.PATH + "ThrustCurve", "a": 1.5}, "thrust_curve.a = 1.5 is out of range: allowed in [0, 1]"),
    ({"_target_": bench_effects.PATH + "BatterySag", "rate": -0.02}, "battery_sag.rate = -0.02 is out of range: allowed >= 0 1/s"),
    ({"_target_": bench_effects.PATH + "Updraft", "speed": float("inf")}, "updraft.speed = inf is out of range: allowed finite m/s"),
    ({"_target_": bench_effects.PATH + "OneSidedDrag", "c": -0.6}, "one_sided_drag.c = -0.6 is out of range: allowed >= 0"),
    ({"_target_": bench_effects.PATH + "Crosstalk", "leak": "much"}, "crosstalk.leak = 'much' is out of range: allowed in [0, 1]"),
])
def test_an_outside_effects_parameter_out_of_range_names_the_key_and_the_range(entry, words):
    from sdexp.errors import UserError
    from sdexp.sim.physics.effects import build_effects
    with pytest.raises(UserError) as info:
        build_effects([entry])
    assert words in str(info.value) and str(info.value).startswith("sim.effects[0] (")


def test_a_tilted_rotor_the_drone_lacks_is_refused():
    from types import SimpleNamespace

    from sdexp.errors import UserError
    tilt = bench_effects.RotorTilt(rotor=9)
    with pytest.raises(UserError, match=r"rotor_tilt.rotor = 9 is out of range: allowed 0 to 3"):
        tilt.setup(SimpleNamespace(drone=SimpleNamespace(num_rotors=4)))
