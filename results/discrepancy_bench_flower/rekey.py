"""Usage (from a checkout at 3109533, PYTHONPATH on it): python rekey.py <scenario_dir> [--write]

Re-key bench rows whose scenario differs from this machine's only in the last bits of floats
(payload points are mass @ rest: a BLAS reduction, machine-dependent in its last bit).
A row is re-keyed only where (1) its stored key equals the key of this run's scenario with the
row's own stored effects put back (so code, configs and everything else match exactly), and
(2) the stored effects equal this machine's to 1e-12 relative."""
import json, sys, numpy as np
from pathlib import Path
from sdexp.eval.run import typed
from hydra import compose, initialize_config_module
with initialize_config_module("sdexp.conf", version_base="1.3"):
    cfg = typed(compose("config", overrides=[   # the README's command
        "experiment=discrepancy_bench", "drone=flower", "sim.element=quadratic", "drone.mesh.edge_length=0.35",
        "experiment.params.levels=[1]", "experiment.params.seeds=1", "experiment.params.nulls=4",
        "experiment.params.combos=true", "experiment.params.variants=1", "experiment.params.unmodelled=1",
        f"experiment.params.scenario_dir={sys.argv[1]}"]))
from sdexp.sim.drone import build_drone
from sdexp.discrepancy.bench import scenarios, LIBRARY, scenario_key, ROW_FILE
drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
p = cfg.experiment.params
scs = scenarios(drone, list(p.effects or LIBRARY), int(p.seeds), int(p.nulls), bool(p.combos), int(p.unmodelled),
                int(cfg.seed), tuple(p.levels or (0, 1)), int(p.variants))
args = [cfg.drone, cfg.sim, cfg.noise, cfg.discrepancy]
def flat(e):
    return np.array([v for x in e for k in sorted(x) if k != "name" for v in np.ravel(x[k]).tolist() if not isinstance(v, str)], float)
for sc in scs:
    f = Path(p.scenario_dir) / sc["id"] / ROW_FILE
    if not f.exists():
        continue
    done = json.loads(f.read_text())
    key = scenario_key(sc, *args)
    if done["key"] == key:
        continue
    old = dict(sc, effects=json.loads(done["row"]["true_effects"]))
    same_rest = scenario_key(old, *args) == done["key"]
    a, b = flat(old["effects"]), flat(sc["effects"])
    close = a.shape == b.shape and np.allclose(a, b, rtol=1e-12, atol=1e-15)
    print(sc["id"], "rest of key matches:", same_rest, "effects within 1e-12:", close, "max diff", np.abs(a - b).max() if a.shape == b.shape and a.size else None)
    if same_rest and close and "--write" in sys.argv:
        done["key"] = key
        done["rekeyed"] = "scenario floats differ from this machine's in the last bits only (results/discrepancy_bench_flower/rekey.py)"
        f.write_text(json.dumps(done))
        print("  re-keyed")
