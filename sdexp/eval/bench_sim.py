"""``sdexp experiment=bench_sim``: simulator speed for every drone, and cost against element
count for the flower refined, with the petal bend under a fixed load at each resolution beside
it (the accuracy the speed is bought with: coarse linear tets are too stiff in bending). Timings
are printed and written, never asserted."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from sdexp.sim.statics import held_bend, outer_rotors
from sdexp.sim.drone import build_drone, drone_names
from sdexp.sim.simulator import Simulator


def load_drone_cfg(name: str):
    from sdexp.config import DroneConfig
    path = Path(__file__).resolve().parents[2] / "conf" / "drone" / f"{name}.yaml"
    return OmegaConf.merge(OmegaConf.structured(DroneConfig), OmegaConf.load(path))


def time_drone(drone, drone_cfg, cfg, seconds: float, seed: int, block: int = 25) -> dict:
    """Wall time of ``seconds`` of simulated flight, timed in blocks of ``block`` control steps:
    the figures are the median block's (this VM's neighbours move single timings by 30-50%),
    with the fastest block's beside them."""
    sim = Simulator(drone, cfg.sim, cfg.noise, seed)
    rng = np.random.default_rng(seed)
    # random thrust holds, as in data generation: the drone tumbles and deforms
    hold = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
    sim.step(hold)  # compile / warm up
    steps = max(block, int(round(seconds / cfg.sim.control_dt)))
    walls = []
    for k in range(steps):
        if k % block == 0:
            t0 = time.perf_counter()
        if k % 100 == 0:
            hold = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
        sim.step(hold)
        if not sim.alive:
            sim.reset()
        if k % block == block - 1:
            walls.append(time.perf_counter() - t0)
    step_wall = np.median(walls) / block
    best = min(walls) / block
    n_el = drone.fem.n_elems
    return {
        "drone": drone_cfg.name, "dim": drone.dim, "elements": n_el, "vertices": len(drone.fem.rest),
        "edge_length": drone_cfg.mesh.edge_length, "substep_ms": 1e3 * sim.dt,
        "substeps_per_step": sim.n_sub,
        "element_substeps_per_s": n_el * sim.n_sub / step_wall,
        "us_per_substep": 1e6 * step_wall / sim.n_sub,
        "realtime_factor": cfg.sim.control_dt / step_wall,
        "realtime_factor_best_block": cfg.sim.control_dt / best,
    }


def run(cfg, out_dir: Path) -> dict:
    from sdexp.eval.plots import bench_plot
    from tqdm import tqdm

    p = cfg.experiment.params
    names = list(p.get("drones") or drone_names())
    rows = []
    for name in tqdm(names, desc="bench_sim drones"):
        d = cfg.drone if name == cfg.drone.name else load_drone_cfg(name)
        drone = build_drone(d, cfg.cache_dir, cfg.sim.element)
        rows.append({"series": "drone", **time_drone(drone, d, cfg, float(p.seconds), int(cfg.seed))})
    for edge in tqdm(list(p.get("scaling_edges", [])), desc="bench_sim scaling"):
        d = load_drone_cfg(p.get("scaling_drone", "flower"))
        d.mesh.edge_length = float(edge)
        drone = build_drone(d, cfg.cache_dir, cfg.sim.element)
        row = time_drone(drone, d, cfg, float(p.scaling_seconds), int(cfg.seed))
        # mean bend of the peripheral sensors, outer rotors pushing bend_load N harder than the rest
        row["bend_deg"] = float(held_bend(drone, cfg.sim, outer_rotors(drone), float(p.bend_load)).mean())
        rows.append({"series": "scaling", **row})
    table = pd.DataFrame(rows)
    table.to_csv(out_dir / "bench_sim.csv", index=False)
    bench_plot(table, out_dir / "bench_sim.png")
    print(table.drop(columns=["series"]).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    out = {}
    for r in rows:
        if r["series"] == "drone":
            out[f"{r['drone']}_realtime_factor"] = r["realtime_factor"]
            out[f"{r['drone']}_element_substeps_per_s"] = r["element_substeps_per_s"]
    return out
