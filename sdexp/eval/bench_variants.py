"""bench_sim's variants: ``sim.precision`` and ``sim.mass_scaling`` on one drone's default mesh.

Speed as ratios, measured in one process with the variants alternated (this VM shares its two
cores with other work: absolute figures move by 1.5x between minutes, ratios of interleaved
timings much less): the force kernel alone (one thread, ns per element-substep, its GFLOP/s
and share of the peak a probe of ours reaches on this core) and whole control steps (the
real-time factor under random thrust holds, as bench_sim times every drone).

Accuracy against the float64, unscaled simulator: a noise-free flight under the same random
holds (vertex position and IMU bend deviation over time), an undamped free vibration (the
energy drift of each variant), and the first eight free-free frequencies that scaling moves.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from sdexp.sim.physics.modes import free_frequencies, stiffness, strain_energy
from sdexp.sim.physics.native import library
from sdexp.sim.simulator import Simulator

log = logging.getLogger(__name__)

# Operations per element and substep in kernels.c's quadratic tet (forces.h: p2_point at four
# quadrature points, two polar iterations each, the gather of 27 node offsets and the scatter of
# 30 forces), counted in the source with a * b + c as 2 and /, sqrt as 1, after the quadrature
# literals fold: about 3,050 (the issue's prototype count: 2,770). Linear tets: about 620.
FLOPS = {10: 3050, 4: 620}
PROBE_ROUNDS = 2_000_000   # probe iterations per timing: ~20 ms at the peak


REFERENCE = {"precision": "float64", "mass_scaling": 0.0}   # the yardstick every variant is timed against


def variants(budget: float) -> dict[str, dict]:
    """The sim overrides of each variant, each spelled out whatever the defaults (the first,
    float64 unscaled, is the reference)."""
    return {"float64": REFERENCE, "float32": {"precision": "float32", "mass_scaling": 0.0},
            "float64 scaled": {"precision": "float64", "mass_scaling": budget},
            "float32 scaled": {"precision": "float32", "mass_scaling": budget}}


def peak_gflops(single: bool, rounds: int = PROBE_ROUNDS) -> float:
    """GFLOP/s of kernels.c's FMA probe (one core, double or float): one timing."""
    lib = library()
    probe = lib.fma_probe_f32 if single else lib.fma_probe
    t0 = time.perf_counter()
    probe(rounds, 1.0)
    return 2.0 * lib.fma_probe_width(int(single)) * rounds / (time.perf_counter() - t0) / 1e9


def _hold(rng, drone) -> np.ndarray:
    return rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust


def time_variants(sims: dict[str, Simulator], seconds: float, seed: int, rounds: int = 60,
                  block: int = 25, reps: int = 4) -> dict[str, dict]:
    """Per variant: the force kernel's ns per element-substep (one thread, ``reps`` evaluations
    a timing, a few ms: the variants take turns ``rounds`` times, so a load that changes over
    seconds falls on all of them alike), with the FMA probe of its type every tenth round; then
    the whole step's wall time in blocks of ``block`` control steps under the same random
    holds as time_drone, the variants' blocks in turn. Medians and bests; the speedups against
    the first variant are medians of the per-round (per-block) ratios."""
    names = list(sims)
    kern = {k: [] for k in names}
    peak = {k: [] for k in names}
    steps = {k: [] for k in names}
    rngs = {k: np.random.default_rng(seed) for k in names}
    holds = {k: _hold(rngs[k], sims[k].drone) for k in names}
    for k in names:
        sims[k].step(holds[k])   # warm up
    for r in range(rounds):
        for k in names:
            sim = sims[k]
            t0 = time.perf_counter()
            sim.body.forces_only(reps)
            kern[k].append(1e9 * (time.perf_counter() - t0) / (reps * sim.fem.n_elems))
            if r % 10 == 0:
                peak[k].append(peak_gflops(sim.body.real is np.float32))
    n_blocks = max(1, int(round(seconds / sims[names[0]].cfg.control_dt / block)))
    blowups = {k: [] for k in names}
    for r in range(n_blocks):
        for k in names:
            sim = sims[k]
            t0 = time.perf_counter()
            for j in range(block):
                if (r * block + j) % 100 == 0:
                    holds[k] = _hold(rngs[k], sim.drone)
                sim.step(holds[k])
                if not sim.alive:
                    blowups[k].append(f"{sim.failure.reason} at {sim.t:.2f} s")
                    sim.reset()
            steps[k].append((time.perf_counter() - t0) / block)
    out, first = {}, names[0]
    for k in names:
        sim = sims[k]
        ns, ns_best = float(np.median(kern[k])), float(min(kern[k]))
        kernel_speedup = float(np.median(np.array(kern[first]) / np.array(kern[k])))
        flops = FLOPS.get(sim.fem.elems.shape[1], np.nan) if sim.fem.dim == 3 else np.nan
        gflops, top = flops / ns_best, max(peak[k])
        # a variant that blew up timed blown-up states and resets, not a flight: no step speed (null), as
        # bench_sim's drone rows; the kernel's figures time the forces of one state and stand
        diverged = bool(blowups[k] or blowups[first])
        out[k] = {"kernel_ns_per_element_substep": ns, "kernel_ns_best": ns_best,
                  "kernel_speedup": kernel_speedup,
                  "step_speedup": None if diverged else float(np.median(np.array(steps[first]) / np.array(steps[k]))),
                  "kernel_gflops": gflops, "peak_gflops": top, "peak_share": gflops / top,
                  "substeps_per_step": sim.n_sub,
                  "realtime_factor": None if blowups[k] else sim.cfg.control_dt / float(np.median(steps[k])),
                  "realtime_factor_best_block": None if blowups[k] else sim.cfg.control_dt / float(min(steps[k])),
                  "blowups": len(blowups[k]), "blowup_detail": "; ".join(blowups[k])}
    return out


def flight_deviation(drone, cfg, overrides: dict, seconds: float, seed: int, every: float = 0.25) -> list[dict]:
    """The variant against float64 unscaled in a noise-free flight under the same random holds:
    every ``every`` s the largest vertex position deviation (m), the largest IMU bend deviation
    (deg), the RMS over the IMUs of the bend and of its deviation (rad), and for scale the
    largest IMU bend of the reference (deg) and how far its centroid has travelled (m): inertia
    added without weight slows every rigid acceleration by the added fraction, so a scaled
    flight drifts from the unscaled one in proportion to the distance flown."""
    noise = replace(cfg.noise, enabled=False)
    ref = Simulator(drone, replace(cfg.sim, **REFERENCE), noise, seed)
    var = Simulator(drone, replace(cfg.sim, **overrides), noise, seed)
    rng = np.random.default_rng(seed)
    rows, hold = [], None
    per = max(1, int(round(every / cfg.sim.control_dt)))
    for k in range(int(round(seconds / cfg.sim.control_dt))):
        if k % 100 == 0:
            hold = _hold(rng, drone)
        ref.step(hold)
        var.step(hold)
        if not (ref.alive and var.alive):
            rows.append({"time": ref.t, "failure": f"{ref.failure or ''} / {var.failure or ''}"})
            break
        if (k + 1) % per == 0:
            s_ref, s_var = ref.state(noisy=False).s, var.state(noisy=False).s
            rows.append({"time": ref.t, "position_deviation": float(np.abs(ref.x - var.x).max()),
                         "bend_deviation_deg": float(np.rad2deg(np.abs(s_ref - s_var).max(initial=0.0))),
                         "bend_deg": float(np.rad2deg(np.abs(s_ref).max(initial=0.0))),
                         "bend_rms_deviation": float(np.sqrt(np.mean((s_ref - s_var) ** 2))) if len(s_ref) else 0.0,
                         "bend_rms": float(np.sqrt(np.mean(s_ref ** 2))) if len(s_ref) else 0.0,
                         "travel": float(np.linalg.norm((ref.x - ref.fem.rest).mean(axis=0)))})
    return rows


def _rms_ratio(rows, num: str, den: str) -> float:
    """sqrt(mean num^2) / sqrt(mean den^2) over a flight's samples."""
    rows = list(rows)
    if not rows:
        return np.nan
    return float(np.sqrt(np.mean([r[num] ** 2 for r in rows]) / max(np.mean([r[den] ** 2 for r in rows]), 1e-300)))


def energy_drift(drone, cfg, overrides: dict, seconds: float, seed: int,
                 excite: float = 0.5) -> tuple[float | None, str]:
    """(largest |E - E0| / E0, "") of an undamped free vibration with no thrust and no gravity, where
    the continuum conserves E (kinetic with the inertial mass, plus the co-rotated strain energy)
    and symplectic Euler keeps it bounded: its drift is the integrator's and the forces' error.
    The start: the float64 drone after ``excite`` s of random holds (deformed, spinning). A body
    that diverges on the way (a substep past the stable one) has no drift to measure: (None, the
    reason), by the simulator's own failure rules (an inverted element, a vertex past
    sim.max_speed, a state not finite) checked before its energy is read: the strain energy's
    SVD of a runaway body's deformation gradients does not converge."""
    noise = replace(cfg.noise, enabled=False)
    base = Simulator(drone, cfg.sim, noise, seed)
    rng = np.random.default_rng(seed)
    hold = _hold(rng, drone)
    for _ in range(int(round(excite / cfg.sim.control_dt))):
        base.step(hold)
        if not base.alive:
            return None, f"energy check: the excitation diverged ({base.failure.reason} at {base.t:.2f} s)"
    sim = Simulator(drone, replace(cfg.sim, **overrides), noise, seed)
    sim.body.x[:], sim.body.v[:], sim.body.q[:] = base.body.x, base.body.v, base.body.q
    body, fem = sim.body, sim.fem

    def energy() -> float:
        return 0.5 * float(np.sum(body.mass[:, None] * body.v ** 2)) + strain_energy(fem, body.x)
    e0, worst = energy(), 0.0
    for k in range(int(round(seconds / cfg.sim.control_dt))):
        inverted, vmax2 = body.run(sim.n_sub, sim.dt)
        why = ("positions or velocities not finite" if not (np.isfinite(vmax2) and np.all(np.isfinite(body.x)))
               else f"{inverted} elements inverted" if inverted > 0
               else f"vertex speed {np.sqrt(vmax2):.1f} m/s > sim.max_speed" if vmax2 > sim.cfg.max_speed ** 2 else "")
        if why:
            return None, f"energy check: the free vibration diverged at {(k + 1) * cfg.sim.control_dt:.2f} s ({why})"
        worst = max(worst, abs(energy() - e0))
    return worst / e0, ""


def frequency_changes(sim: Simulator, k: int = 8) -> np.ndarray:
    """The first k free-free frequencies' relative change under the simulator's added inertia."""
    if sim.scaling.added is None:
        return np.zeros(k)
    K = stiffness(sim.fem)
    f0 = free_frequencies(sim.fem, K=K, k=k)
    return free_frequencies(sim.fem, sim.fem.mass + sim.scaling.added, K=K, k=k) / f0 - 1


def run_variants(drone, drone_cfg, cfg, p) -> list[dict]:
    """bench_sim's variant rows for one drone: speed (ratios to float64 unscaled), the scaling's
    cost, the float32 flight's deviation and every variant's energy drift."""
    seed = int(cfg.seed)
    specs = variants(float(p.mass_scaling))
    sims = {k: Simulator(drone, replace(cfg.sim, **o), cfg.noise, seed) for k, o in specs.items()}
    timing = time_variants(sims, float(p.variants_seconds), seed)
    rows = []
    for k, o in specs.items():
        sim, t = sims[k], timing[k]
        freq = frequency_changes(sim)
        dev = flight_deviation(drone, cfg, o, float(p.deviation_seconds), seed) if o != REFERENCE else []
        at = {round(r["time"], 2): r for r in dev if "position_deviation" in r}
        drift, drift_why = energy_drift(drone, cfg, o, 1.0, seed)
        rows.append({
            "series": "variant", "drone": drone_cfg.name, "variant": k, "element": "quadratic",
            "elements": sim.fem.n_elems, **t,
            "added_mass_fraction": sim.scaling.fraction, "step_gain": sim.scaling.gain,
            "frequency_change_max": float(np.abs(freq).max()),
            "frequency_changes": " ".join(f"{v:+.4f}" for v in freq),
            "position_deviation_1s": at.get(1.0, {}).get("position_deviation", np.nan),
            "position_deviation_end": max((r["position_deviation"] for r in at.values()), default=np.nan),
            "bend_deviation_deg_max": max((r["bend_deviation_deg"] for r in at.values()), default=np.nan),
            "bend_deg_max": max((r["bend_deg"] for r in at.values()), default=np.nan),
            "bend_rms_deviation": _rms_ratio(at.values(), "bend_rms_deviation", "bend_rms"),
            "travel": max((r["travel"] for r in at.values()), default=np.nan),
            "deviation_failure": next((r["failure"] for r in dev if "failure" in r), ""),
            "energy_drift": drift,   # null where the body diverged: the reason in blowup_detail
            "blowup_detail": "; ".join(filter(None, [t["blowup_detail"], drift_why])),
        })

        def shown(v, form: str) -> str:
            return "null" if v is None else format(v, form)
        log.info(f"  {drone_cfg.name} {k}: kernel {t['kernel_ns_per_element_substep']:.1f} ns/element-substep "
                 f"(x{rows[-1]['kernel_speedup']:.2f}, {t['kernel_gflops']:.1f} GFLOP/s, "
                 f"{t['peak_share']:.0%} of the {t['peak_gflops']:.0f} GFLOP/s probe), step "
                 f"x{shown(t['step_speedup'], '.2f')} ({shown(t['realtime_factor'], '.2f')}x real time, "
                 f"{t['substeps_per_step']} substeps, {t['blowups']} blow-ups), "
                 f"+{sim.scaling.fraction:.2%} mass for x{sim.scaling.gain:.2f} step, frequencies "
                 f"{rows[-1]['frequency_changes']}, energy drift {shown(drift, '.3%')}"
                 + (f"; {rows[-1]['blowup_detail']}" if rows[-1]["blowup_detail"] else ""))
    return rows
