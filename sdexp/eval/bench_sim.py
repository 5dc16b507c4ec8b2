"""``sdexp experiment=bench_sim``: simulator speed for every drone with both element types, and
the speed/accuracy frontier of the flower refined. Beside every timing the accuracy it is bought
with: the IMU bend and the compliance under a fixed load (sdexp.eval.convergence) and their
errors against the converged body (Richardson over three refined quadratic meshes, cached). Timings are
printed and written, never asserted; a blow-up during a timing is counted in the CSV.

``experiment.params.models`` adds the reduced-order model (``sim.model=reduced``, built with
``sim.reduced.*``) to the drone rows: a row per drone, element and model, the models timed in one
process block by block under the same thrust holds, the reduced row with its speed-up over the
full one (the median of the per-block ratios: this VM's neighbours move absolute timings by
30-50%, ratios of interleaved blocks much less), its cubature's element count and its linear
statics against the full model's (``sdexp.eval.convergence.reduced_static_errors``). A model that
refuses the config (the reduced one: ground, obstacles, mass scaling) is a row with its reason."""
from __future__ import annotations

import logging
import os
import time
from dataclasses import replace

import numpy as np
import pandas as pd
from sdexp.eval.convergence import converged_response, response_errors
from sdexp import conf
from sdexp.errors import UserError
from sdexp.eval.run import Run
from sdexp.sim.drone import build_drone, drone_names
from sdexp.sim.simulator import Simulator

log = logging.getLogger(__name__)


SPEED = ("element_substeps_per_s", "us_per_substep", "realtime_factor", "realtime_factor_best_block")
# columns that are numbers or null (None where a run blew up or a model refused): NaN in the table
NUMERIC = (*SPEED, "speedup_vs_full", "step_speedup", "energy_drift")


def sim_config(sim_cfg, model: str):
    """``sim_cfg`` with ``sim.model = model`` (as given where it already is)."""
    return sim_cfg if sim_cfg.model == model else replace(sim_cfg, model=model)


def simulators(drone, cfg, models, seed: int) -> dict:
    """A Simulator per model, or, for a model that refuses the config (the reduced one: contact,
    mass scaling, effects that change the model), the refusal's text. The full model's own
    errors are the config's and raise."""
    out = {}
    for model in models:
        try:
            out[model] = Simulator(drone, sim_config(cfg.sim, model), cfg.noise, seed)
        except UserError as err:
            if model == "full":
                raise
            log.warning(f"bench_sim: {drone.name}, sim.model = {model} refused: {err}")
            out[model] = f"refused: {err}"
    return out


def thrust_holds(drone, steps: int, seed: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """The warm-up hold and one hold per control step: random thrust holds, as in data
    generation (the drone tumbles and deforms), redrawn every 100 steps."""
    rng = np.random.default_rng(seed)
    warm = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
    holds = []
    for k in range(steps):
        if k % 100 == 0:
            hold = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
        holds.append(hold)
    return warm, holds


def time_models(drone, drone_cfg, cfg, sims: dict, seconds: float, seed: int, block: int = 25) -> dict[str, dict]:
    """Wall time of ``seconds`` of simulated flight on each of ``sims`` (a model's Simulator, or
    its refusal's text: a row with that reason), in blocks of ``block`` control steps, the
    models' blocks in turn (which goes first alternates) under the same thrust holds: the
    figures are the median block's (this VM's neighbours move single timings by 30-50%), with
    the fastest block's beside them; a model beside the full one also gets ``speedup_vs_full``,
    the median of the per-block ratios. A blow-up resets the drone and is counted; a model
    that blew up has no speed (null), and no speed-up. A reduced flight that leaves the range
    its model was fitted on (the holds are the paper's +-Tmax, past where the reduced model is
    valid: docs/reduced_model.md) is a recorded failure, not a divergence: counted in
    ``left_range`` and restarted, its speed kept (a substep's cost does not depend on the state;
    the resets' own time is left out of the blocks)."""
    live = {m: s for m, s in sims.items() if not isinstance(s, str)}
    load = os.getloadavg()[0]
    n_blocks = max(1, int(round(seconds / cfg.sim.control_dt)) // block)
    warm, holds = thrust_holds(drone, n_blocks * block, seed)
    for sim in live.values():
        sim.step(warm)   # compile / warm up
        if not sim.alive:
            sim.reset()
    walls = {m: [] for m in live}
    blowups = {m: [] for m in live}
    left = {m: [] for m in live}
    names = list(live)
    for b in range(n_blocks):
        for m in (names if b % 2 == 0 else names[::-1]):
            sim = live[m]
            resets = 0.0
            t0 = time.perf_counter()
            for k in range(b * block, (b + 1) * block):
                sim.step(holds[k])
                if not sim.alive:
                    t1 = time.perf_counter()
                    reason = sim.failure.reason
                    (left if reason == "left_reduced_range" else blowups)[m].append(f"{reason} at {sim.t:.2f} s")
                    sim.reset()
                    resets += time.perf_counter() - t1
            walls[m].append(time.perf_counter() - t0 - resets)
    rows = {}
    for m, sim in sims.items():
        if isinstance(sim, str):
            rows[m] = {**mesh_row(drone, drone_cfg, m), "substep_ms": None, "substeps_per_step": None,
                       **dict.fromkeys(SPEED), "blowups": None, "blowup_detail": "", "basis": None,
                       "left_range": None, "speedup_vs_full": None, "reason": sim}
            continue
        step_wall = np.median(walls[m]) / block
        best = min(walls[m]) / block
        n_el = evaluated_elements(drone, sim)
        speed = dict(zip(SPEED, (n_el * sim.n_sub / step_wall, 1e6 * step_wall / sim.n_sub,
                                 cfg.sim.control_dt / step_wall, cfg.sim.control_dt / best)))
        if blowups[m]:
            # a diverged run's blocks time blown-up states and resets, not a flight: no speed to report
            # (null in the CSV, metrics.json and the plot alike), the blow-ups counted instead
            speed = dict.fromkeys(speed, None)
        rows[m] = {**stepping(drone, drone_cfg, sim, m), **speed, "blowups": len(blowups[m]),
                   "blowup_detail": "; ".join(blowups[m] + left[m])}
        if m != "full":
            rows[m]["basis"] = int(sim.reduced.r) if sim.reduced is not None else None
            rows[m]["left_range"] = len(left[m])
            ok = "full" in live and not blowups["full"] and not blowups[m]
            rows[m]["speedup_vs_full"] = float(np.median(np.array(walls["full"]) / np.array(walls[m]))) if ok else None
    # the machine's load beside the figures (the neighbours' share of the cores moves them)
    log.info(f"bench_sim: {drone_cfg.name} timed ({', '.join(live)}) under a load average of {load:.1f} -> "
             f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    return rows


def time_drone(drone, drone_cfg, cfg, seconds: float, seed: int, block: int = 25) -> dict:
    """The full model's row of time_models (the simulator as ``cfg.sim`` gives it)."""
    return time_models(drone, drone_cfg, cfg, simulators(drone, cfg, ["full"], seed), seconds, seed, block)["full"]


def evaluated_elements(drone, sim) -> int:
    """The elements a substep evaluates: the mesh's, or the reduced model's cubature set."""
    return drone.fem.n_elems if sim.reduced is None else len(sim.reduced.elements)


def mesh_row(drone, drone_cfg, model: str = "full") -> dict:
    """The row's drone, mesh and model."""
    return {"drone": drone_cfg.name, "element": "quadratic" if drone.fem.order == 2 else "linear", "model": model,
            "dim": drone.dim, "elements": drone.fem.n_elems if model == "full" else None,
            "nodes": len(drone.fem.rest), "edge_length": drone_cfg.mesh.edge_length}


def stepping(drone, drone_cfg, sim, model: str = "full") -> dict:
    """What a mesh costs without timing it: elements (a reduced model's: its cubature's) and
    the substeps of its stable step."""
    return {**mesh_row(drone, drone_cfg, model), "elements": evaluated_elements(drone, sim),
            "substep_ms": 1e3 * sim.dt, "substeps_per_step": sim.n_sub}


def reduced_errors(drone, sim, gravity: float, load: float) -> dict:
    """A reduced row's accuracy: its linear statics under the accuracy load against the full
    model's on the same mesh (convergence.reduced_static_errors: the step's rest stiffness)."""
    from sdexp.eval.convergence import reduced_static_errors
    if isinstance(sim, str) or sim.reduced is None:
        return {}
    return {f"{k}_vs_full": v for k, v in reduced_static_errors(drone, sim.reduced, gravity, load).items()}


def with_edge(drone_cfg, edge_length: float):
    """The drone config meshed at another edge length."""
    return replace(drone_cfg, mesh=replace(drone_cfg.mesh, edge_length=float(edge_length)))


def drone_config(cfg, name: str):
    """The run's drone (with its overrides) if it is ``name``, else conf/drone/<name>.yaml."""
    return cfg.drone if name == cfg.drone.name else conf.drone(name)


def check(run: Run) -> None:
    """Before anything is written: the bench names its models itself (its other series and the
    variants are the full model's)."""
    model = run.cfg.sim.model
    if model != "full":
        raise UserError(f"sim.model = {model}: bench_sim times the models experiment.params.models names "
                        f"(e.g. [full,reduced]), each beside the full one: allowed sim.model = full here")


def run(run: Run) -> dict:
    from sdexp.eval.bench_variants import run_variants
    from sdexp.eval.plots import bench_plot, variants_plot
    from sdexp.log import Phase

    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    names = drone_names() if p.drones is None else list(p.drones)   # [] = none (e.g. the variants alone)
    elements = list(p.elements)
    gravity, load = float(cfg.sim.gravity), float(p.bend_load)
    models = list(p.models)
    rows = []
    for name in Phase("bench_sim drones", len(names), "drones").iterate(names):
        d = drone_config(cfg, name)
        ref = converged_response(d, cfg.cache_dir, p.refine[f"{d.dim}d"], gravity, load)
        for element in elements:
            drone = build_drone(d, cfg.cache_dir, element)
            sims = simulators(drone, cfg, models, int(cfg.seed))
            timed = time_models(drone, d, cfg, sims, float(p.seconds), int(cfg.seed))
            for model in models:
                accuracy = response_errors(drone, ref, gravity, load) if model == "full" else \
                    reduced_errors(drone, sims[model], gravity, load)
                rows.append({"series": "drone", **timed[model], **accuracy})
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
        rows += [{**r, "model": "full"} for r in run_variants(build_drone(d, cfg.cache_dir, "quadratic"), d, cfg, p)]
    table = pd.DataFrame(rows)
    for c in NUMERIC:   # a blown-up run's null speeds: NaN in a numeric column, as the plot reads it
        if c in table:
            table[c] = pd.to_numeric(table[c])
    run.table(table, "bench_sim")
    if (table["series"] != "variant").any():
        bench_plot(table[table["model"] == "full"], out_dir / "bench_sim.png")   # the full model's figure
        show = ["series", "drone", "element", "model", "elements", "substeps_per_step", "us_per_substep",
                "realtime_factor", "speedup_vs_full", "element_substeps_per_s", "bend_error", "compliance_error",
                "bend_error_vs_full", "compliance_error_vs_full", "blowups", "left_range", "reason"]
        log.info(table[table["series"] != "variant"][[c for c in show if c in table]].to_string(
            index=False, float_format=lambda v: f"{v:.4g}"))
    if variant_drones:
        variants_plot(table, out_dir / "variants.png")
        show = ["drone", "variant", "kernel_ns_per_element_substep", "kernel_speedup", "kernel_gflops", "peak_share",
                "substeps_per_step", "realtime_factor", "step_speedup", "added_mass_fraction", "step_gain",
                "frequency_change_max", "position_deviation_end", "travel", "bend_deviation_deg_max",
                "bend_rms_deviation", "energy_drift"]
        log.info(table[table["series"] == "variant"][show].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return metrics(rows)


def metrics(rows: list[dict]) -> dict:
    """metrics.json: each benchmarked drone's speed (null where it blew up or was not measured),
    accuracy and blow-ups (another model's under <drone>_<element>_<model>_..., with its speed-up);
    each variant's speed-ups and deviations (sim.precision, sim.mass_scaling)."""
    out = {}
    for r in rows:
        if r["series"] == "drone" and r.get("model", "full") != "full":
            tag = f"{r['drone']}_{r['element']}_{r['model']}"
            for key in ("realtime_factor", "speedup_vs_full", "substeps_per_step", "elements", "blowups",
                        "left_range", "bend_error_vs_full", "compliance_error_vs_full"):
                out[f"{tag}_{key}"] = r.get(key)
            continue
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
    # what was not measured (a diverged flight's deviations, a 2D kernel's GFLOP/s) is null, as JSON has it
    return {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in out.items()}
