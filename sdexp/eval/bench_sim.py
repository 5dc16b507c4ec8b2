"""``sdexp experiment=bench_sim``: simulator speed for every drone with both element types, and
the speed/accuracy frontier of the flower refined. Beside every timing the accuracy it is bought
with: the IMU bend and the compliance under a fixed load (sdexp.eval.convergence) and their
errors against the converged body (Richardson over three refined quadratic meshes, cached). Timings are
printed and written, never asserted; a blow-up during a timing is counted in the CSV."""
from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np
import pandas as pd
from sdexp.eval.convergence import converged_response, response_errors
from sdexp import conf
from sdexp.eval.run import Run
from sdexp.sim.drone import build_drone, drone_names
from sdexp.sim.simulator import Simulator

log = logging.getLogger(__name__)


SPEED = ("element_substeps_per_s", "us_per_substep", "realtime_factor", "realtime_factor_best_block")


def time_drone(drone, drone_cfg, cfg, seconds: float, seed: int, block: int = 25) -> dict:
    """Wall time of ``seconds`` of simulated flight, timed in blocks of ``block`` control steps:
    the figures are the median block's (this VM's neighbours move single timings by 30-50%),
    with the fastest block's beside them. A blow-up resets the drone and is counted."""
    sim = Simulator(drone, cfg.sim, cfg.noise, seed)
    rng = np.random.default_rng(seed)
    # random thrust holds, as in data generation: the drone tumbles and deforms
    hold = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
    sim.step(hold)  # compile / warm up
    steps = max(block, int(round(seconds / cfg.sim.control_dt)))
    walls, blowups = [], []
    for k in range(steps):
        if k % block == 0:
            t0 = time.perf_counter()
        if k % 100 == 0:
            hold = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
        sim.step(hold)
        if not sim.alive:
            blowups.append(f"{sim.failure.reason} at {sim.t:.2f} s")
            sim.reset()
        if k % block == block - 1:
            walls.append(time.perf_counter() - t0)
    step_wall = np.median(walls) / block
    best = min(walls) / block
    n_el = drone.fem.n_elems
    speed = dict(zip(SPEED, (n_el * sim.n_sub / step_wall, 1e6 * step_wall / sim.n_sub,
                             cfg.sim.control_dt / step_wall, cfg.sim.control_dt / best)))
    if blowups:
        # a diverged run's blocks time blown-up states and resets, not a flight: no speed to report
        # (null in the CSV, metrics.json and the plot alike), the blow-ups counted instead
        speed = dict.fromkeys(speed, None)
    return {**stepping(drone, drone_cfg, sim), **speed, "blowups": len(blowups), "blowup_detail": "; ".join(blowups)}


def stepping(drone, drone_cfg, sim) -> dict:
    """What a mesh costs without timing it: elements and the substeps of its stable step."""
    return {"drone": drone_cfg.name, "element": "quadratic" if drone.fem.order == 2 else "linear",
            "dim": drone.dim, "elements": drone.fem.n_elems, "nodes": len(drone.fem.rest),
            "edge_length": drone_cfg.mesh.edge_length, "substep_ms": 1e3 * sim.dt,
            "substeps_per_step": sim.n_sub}


def with_edge(drone_cfg, edge_length: float):
    """The drone config meshed at another edge length."""
    return replace(drone_cfg, mesh=replace(drone_cfg.mesh, edge_length=float(edge_length)))


def drone_config(cfg, name: str):
    """The run's drone (with its overrides) if it is ``name``, else conf/drone/<name>.yaml."""
    return cfg.drone if name == cfg.drone.name else conf.drone(name)


def run(run: Run) -> dict:
    from sdexp.eval.bench_variants import run_variants
    from sdexp.eval.plots import bench_plot, variants_plot
    from sdexp.log import Phase

    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    names = drone_names() if p.drones is None else list(p.drones)   # [] = none (e.g. the variants alone)
    elements = list(p.elements)
    gravity, load = float(cfg.sim.gravity), float(p.bend_load)
    rows = []
    for name in Phase("bench_sim drones", len(names), "drones").iterate(names):
        d = drone_config(cfg, name)
        ref = converged_response(d, cfg.cache_dir, p.refine[f"{d.dim}d"], gravity, load)
        for element in elements:
            drone = build_drone(d, cfg.cache_dir, element)
            rows.append({"series": "drone", **time_drone(drone, d, cfg, float(p.seconds), int(cfg.seed)),
                         **response_errors(drone, ref, gravity, load)})
    for name in Phase("bench_sim resolutions", len(names), "drones", enabled=bool(p.resolution_factors)).iterate(
            names if p.resolution_factors else []):
        d = drone_config(cfg, name)
        ref = converged_response(d, cfg.cache_dir, p.refine[f"{d.dim}d"], gravity, load)
        for factor in p.resolution_factors:
            coarse = with_edge(d, float(d.mesh.edge_length) * factor)
            drone = build_drone(coarse, cfg.cache_dir, "quadratic")
            sim = Simulator(drone, cfg.sim, cfg.noise, 0)
            rows.append({"series": "resolution", **stepping(drone, coarse, sim), "factor": factor,
                         **response_errors(drone, ref, gravity, load)})
    scaling = p.scaling_drone
    if scaling:
        base = drone_config(cfg, scaling)
        ref = converged_response(base, cfg.cache_dir, p.refine[f"{base.dim}d"], gravity, load)
        for element in elements:
            edges = list(p.scaling_edges[element])
            for edge in Phase(f"bench_sim {scaling} {element}", len(edges), "mesh sizes").iterate(edges):
                d = with_edge(base, edge)
                drone = build_drone(d, cfg.cache_dir, element)
                rows.append({"series": "scaling", **time_drone(drone, d, cfg, float(p.scaling_seconds), int(cfg.seed)),
                             **response_errors(drone, ref, gravity, load)})
    variant_drones = list(p.variants_drones or [])
    for name in Phase("bench_sim variants", len(variant_drones), "drones", enabled=bool(variant_drones)).iterate(
            variant_drones):
        d = drone_config(cfg, name)
        rows += run_variants(build_drone(d, cfg.cache_dir, "quadratic"), d, cfg, p)
    table = pd.DataFrame(rows)
    for c in SPEED:   # a blown-up run's null speeds: NaN in a numeric column, as the plot reads it
        if c in table:
            table[c] = pd.to_numeric(table[c])
    run.table(table, "bench_sim")
    if (table["series"] != "variant").any():
        bench_plot(table, out_dir / "bench_sim.png")
        show = ["series", "drone", "element", "elements", "substeps_per_step", "realtime_factor",
                "element_substeps_per_s", "bend_error", "compliance_error", "blowups"]
        log.info(table[table["series"] != "variant"][show].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if variant_drones:
        variants_plot(table, out_dir / "variants.png")
        show = ["drone", "variant", "kernel_ns_per_element_substep", "kernel_speedup", "kernel_gflops", "peak_share",
                "substeps_per_step", "realtime_factor", "step_speedup", "added_mass_fraction", "step_gain",
                "frequency_change_max", "position_deviation_end", "travel", "bend_deviation_deg_max",
                "bend_rms_deviation", "energy_drift"]
        log.info(table[table["series"] == "variant"][show].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return metrics(rows)


def metrics(rows: list[dict]) -> dict:
    """metrics.json: each benchmarked drone's speed (null where it blew up), accuracy and blow-ups;
    each variant's speed-ups and deviations (sim.precision, sim.mass_scaling)."""
    out = {}
    for r in rows:
        if r["series"] == "drone":
            tag = f"{r['drone']}_{r['element']}"
            out[f"{tag}_realtime_factor"] = r["realtime_factor"]
            out[f"{tag}_element_substeps_per_s"] = r["element_substeps_per_s"]
            out[f"{tag}_bend_error"] = r["bend_error"]
            out[f"{tag}_compliance_error"] = r["compliance_error"]
            out[f"{tag}_blowups"] = r["blowups"]
        if r["series"] == "variant":
            tag = f"{r['drone']}_{r['variant'].replace(' ', '_')}"
            for key in ("kernel_speedup", "step_speedup", "realtime_factor", "kernel_gflops", "peak_share",
                        "step_gain", "added_mass_fraction", "frequency_change_max", "position_deviation_end",
                        "bend_deviation_deg_max", "bend_rms_deviation", "energy_drift"):
                out[f"{tag}_{key}"] = r[key]
    return out
