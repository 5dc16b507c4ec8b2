"""Reduced configs of the control experiments and their stored reference metrics (test-only:
the package ships none).

The test suite runs every experiment below on a tiny rod (or star) model for fractions of a
second and compares its metrics with ``results/reference/<experiment>.json``: two-sided for the
parts that involve no training (the rigid baselines, the simulator), one-sided for the parts
that do (the learned model, ours, the neural controller: "no worse than the reference").
Regenerate the references after an intended change with

    python -m tests.eval.references            # all, or: ... sota nsweep
"""
from __future__ import annotations

import json
import logging
import sys
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)


REFERENCE_DIR = Path(__file__).resolve().parents[2] / "results" / "reference"

# a model trained in seconds: 800 transitions of the rod, 2 epochs of a 16-wide network
SHRUNK = ["drone=rod", "data.samples=800", "data.episode_seconds=1.0", "data.hold_seconds=0.5",
          "data.workers=1", "data.validation_fraction=0.25", "model.epochs=2", "model.hidden=16",
          "model.blocks=1", "model.batch_size=64", "model.threads=1", "sim.threads=1"]
NEURAL = ["control.neural.iterations=2", "control.neural.horizon=3", "control.neural.batch=4"]

REDUCED = {
    "sota": ["experiment.params.seconds=0.3", "experiment.params.start=[0,0]", "experiment.params.target=[1,1]", *NEURAL],
    "nsweep": ["experiment.params.seconds=0.2", "experiment.params.start=[0,0]", "experiment.params.target=[1,0]",
               "experiment.params.n_values=[1,5]"],
    "ablation_fixed_point": ["experiment.params.seconds=0.2", "experiment.params.trials=64",
                             "experiment.params.descent_steps=20", "experiment.params.noise_levels=[0,0.8]"],
    "hover_deform": ["experiment.params.settle_seconds=0.05", "experiment.params.ramp_seconds=0.05",
                     "experiment.params.hold_seconds=0.02"],
    "bench_control": ["experiment.params.samples=10"],
    "obstacle": ["drone=star", "experiment.params.seconds=0.1", "experiment.params.fold_start=0.0",
                 "experiment.params.fold_seconds=0.05"],
    # two small drones, one seed, each with SHRUNK's 800 transitions (no per-channel rule), one at a time
    "fleet": ["experiment.params.drones=[rod,engine]", "experiment.params.seeds=[0]",
              "experiment.params.samples_per_channel=null", "experiment.params.workers=1",
              "experiment.params.recipes.rod.data.samples=800",   # the rod's recipe, on SHRUNK's data
              "experiment.params.hover_seconds=0.3", "experiment.params.reach_seconds=0.3",
              "experiment.params.ramp_seconds=0.1", "experiment.params.velocity_seconds=0.2",
              "experiment.params.settle_seconds=0.05", "experiment.params.deform_ramp_seconds=0.05",
              "experiment.params.deform_hold_seconds=0.1"],
}

# metric -> how a fresh reduced run is compared with the reference:
#   "equal"  two-sided, |new - ref| <= 1e-3 (1 + |ref|): no training involved
#   "lower"  new >= ref - tol (survival: more is better);  "upper"  new <= ref + tol (errors)
CHECKS = {
    "sota": {"rigid_lqr_survival_time": "equal", "rigid_lqr_final_error": "equal",
             "rigid_lqr_thrust_usage": "equal", "geometry_lqr_final_error": "equal",
             "ours_survival_time": "lower", "ours_final_error": "upper", "neural_survival_time": "lower"},
    "nsweep": {"n1_survival_time": "lower", "n5_survival_time": "lower", "n5_final_error": "upper"},
    "ablation_fixed_point": {"relinearized_0_survival_time": "lower", "relinearized_80_survival_time": "lower",
                             "relinearized_0_final_error": "upper"},
    "hover_deform": {"flight_survival_time": "lower", "max_position_deviation_cm": "upper"},
    "bench_control": {},   # timings: printed, never asserted
    "fleet": {"rod_hover_rigid_lqr_final_error_median": "equal", "engine_reach_rigid_lqr_final_error_median": "equal",
              "rod_deform_rigid_lqr_bend_rms_deg_median": "equal",
              "rod_hover_ours_survived": "lower", "engine_velocity_ours_survived": "lower",
              "rod_hover_ours_final_error_median": "upper", "rod_deform_ours_bend_rms_deg_median": "upper",
              "engine_deform_ours_beyond": "equal"},
    "obstacle": {"fold_limit_deg": "equal", "width_reduction_percent": "lower", "flight_survival_time": "lower", "max_z_deviation_m": "upper"},
}


def reduced_overrides(experiment: str, cache_dir: str) -> list[str]:
    return [*SHRUNK, f"cache_dir={cache_dir}", f"experiment={experiment}", *REDUCED[experiment]]


def compare(experiment: str, metrics: dict, reference: dict, rel_tol: float = 0.25, abs_tol: float = 0.05) -> list[str]:
    """Messages for every checked metric outside its tolerance (empty: all within)."""
    bad = []
    for key, kind in CHECKS[experiment].items():
        new, ref = float(metrics[key]), float(reference[key])
        tol = rel_tol * abs(ref) + abs_tol
        ok = {"equal": abs(new - ref) <= 1e-3 * (1 + abs(ref)), "lower": new >= ref - tol, "upper": new <= ref + tol}[kind]
        if not ok:
            bad.append(f"{experiment}.{key} = {new:.6g}, reference {ref:.6g} ({kind})")
    return bad


def regenerate(experiments, cache_dir: str | None = None) -> None:
    from sdexp.eval.run import run_experiment
    from tests.conftest import make_cfg

    cache_dir = cache_dir or tempfile.mkdtemp(prefix="sdexp-ref-")
    REFERENCE_DIR.mkdir(parents=True, exist_ok=True)
    for name in experiments:
        cfg = make_cfg(*reduced_overrides(name, cache_dir))
        with tempfile.TemporaryDirectory() as out:
            metrics = run_experiment(cfg, Path(out))
        keep = {k: metrics[k] for k in CHECKS[name]}
        (REFERENCE_DIR / f"{name}.json").write_text(json.dumps(keep, indent=2, default=float) + "\n")
        log.info(f"sdexp: wrote {REFERENCE_DIR / f'{name}.json'}")


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    regenerate(sys.argv[1:] or list(REDUCED))
