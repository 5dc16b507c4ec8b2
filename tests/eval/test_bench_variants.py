"""bench_sim's variant rows (sdexp.eval.bench_variants)."""


def test_bench_sims_energy_check_reports_a_blown_up_body_as_no_drift_with_its_reason(cache_dir):
    """experiment=bench_sim drone=rod sim.substep=0.01 ended in numpy's 'SVD did not converge'
    inside the energy check; a substep past the stable one is a diverged row: no drift (null),
    the reason instead (the simulator's failure rules, checked before the energy is read)."""
    from sdexp.eval.bench_variants import energy_drift
    from sdexp.sim.drone import build_drone
    from tests.conftest import make_config
    cfg = make_config("drone=rod", "sim.substep=0.01", f"cache_dir={cache_dir}")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    drift, why = energy_drift(drone, cfg, {}, 0.2, 0)
    assert drift is None and why.startswith("energy check: the excitation diverged ("), why
