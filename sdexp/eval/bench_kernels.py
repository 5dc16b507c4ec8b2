"""The compiled step against an earlier commit's, side by side in one process (issue 25):
``python -m sdexp.eval.bench_kernels --against <commit>``.

The commit's kernels.c and forces.h are built with this tree's flags into a temporary folder and
its integrator.py is loaded as a module of its own (its Body with this tree's fem and native:
good for commits whose Body and Step these still fit, such as issue 25's base). Both step the
default flower (or ``--drone``) on one thread under the same random thrust holds: first whether
the two stay bitwise equal (positions and velocities after every control step; else how far
apart after 0.6 s), then the force kernel alone (``forces_only``,
ns per element-substep) and whole control steps, the two taking turns every few milliseconds
(kernel) or 10 control steps (step), so a load that changes over seconds falls on both alike.
Speedups are medians of the per-turn ratios; GFLOP/s and the share of the FMA probe's peak
count bench_variants.FLOPS per element-substep. Pin it to one core (taskset) on a shared machine.
"""
from __future__ import annotations

import argparse
import ctypes
import importlib.util
import logging
import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import sdexp.sim.simulator as simulator
from sdexp import conf
from sdexp.config import NoiseConfig, SimConfig
from sdexp.eval.bench_variants import FLOPS, peak_gflops
from sdexp.sim.drone import build_drone
from sdexp.sim.physics import native
from sdexp.sim.physics.integrator import Body

PHYSICS = "sdexp/sim/physics"
log = logging.getLogger(__name__)


def load_commit(commit: str, folder: Path):
    """(Body class, compiled library) of ``commit``'s integrator.py and kernels.c."""
    root = Path(subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=Path(__file__).parent,
                               check=True, capture_output=True, text=True).stdout.strip())
    for name in ("kernels.c", "forces.h", "integrator.py"):
        text = subprocess.run(["git", "show", f"{commit}:{PHYSICS}/{name}"], cwd=root, check=True,
                              capture_output=True, text=True).stdout
        (folder / name).write_text(text)
    so = folder / "kernels.so"
    subprocess.run([os.environ.get("CC", "gcc"), *native.FLAGS, "-o", str(so), str(folder / "kernels.c"), "-lm"],
                   check=True, capture_output=True, text=True)
    lib = ctypes.CDLL(str(so))
    lib.advance.restype = ctypes.c_int
    lib.advance.argtypes = [ctypes.POINTER(native.Step), ctypes.POINTER(ctypes.c_double)]
    lib.forces_only.argtypes = [ctypes.POINTER(native.Step), ctypes.c_int64]
    spec = importlib.util.spec_from_file_location(f"integrator_{commit}", folder / "integrator.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.Body, lib


def _simulator(drone, precision: str, body_class, lib, threads: int = 1, **sim):
    simulator.Body = body_class   # the Simulator builds its body through this name
    try:
        s = simulator.Simulator(drone, SimConfig(threads=threads, precision=precision, **sim),
                                NoiseConfig(enabled=False), 0)
    finally:
        simulator.Body = Body
    s.body._lib = lib
    return s


def first_difference(drone, old, precision: str, steps: int, threads: int = 1, seed: int = 0, **sim):
    """Steps ``old`` (load_commit's pair) and this tree's step side by side, noise-free, ``steps``
    control steps under random thrust holds (new every 10 steps): (the first control step after
    which positions or velocities differ in any bit, or the failures (speed, inversion), None
    if none; the largest position
    difference at the end; the lowest vertex height seen, to tell that a ground was reached).
    ``sim``: more SimConfig fields (ground, obstacles, mass_scaling, element)."""
    sims = [_simulator(drone, precision, *old, threads=threads, **sim),
            _simulator(drone, precision, Body, native.library(), threads=threads, **sim)]
    rng = np.random.default_rng(seed)
    first, lowest, hold = None, np.inf, None
    for j in range(steps):
        if j % 10 == 0:
            hold = rng.uniform(-1, 1, drone.num_rotors) * drone.max_thrust
        for s in sims:
            s.step(hold)
        a, b = (s.body for s in sims)
        if first is None and not (np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)
                                  and sims[0].failure == sims[1].failure):
            first = j
        lowest = min(lowest, float(b.x[:, 1].min()))
    return first, float(np.abs(sims[0].body.x - sims[1].body.x).max()), lowest


def compare(drone, old, precision: str, seconds: float = 0.6, rounds: int = 100, blocks: int = 60,
            seed: int = 0) -> dict:
    first, deviation, _ = first_difference(drone, old, precision, int(round(seconds / 0.01)), seed=seed)
    sims = {"before": _simulator(drone, precision, *old),
            "after": _simulator(drone, precision, Body, native.library())}
    hold = np.random.default_rng(seed).uniform(-1, 1, drone.num_rotors) * drone.max_thrust
    kern = {k: [] for k in sims}
    step = {k: [] for k in sims}
    peak = []
    ne = sims["after"].fem.n_elems
    for r in range(rounds):
        for k, s in sims.items():
            t0 = time.perf_counter()
            s.body.forces_only(4)
            kern[k].append(1e9 * (time.perf_counter() - t0) / (4 * ne))
        if r % 10 == 0:
            peak.append(peak_gflops(precision == "float32"))
    for r in range(blocks):
        for k, s in sims.items():
            t0 = time.perf_counter()
            for _ in range(10):
                s.step(hold)
            step[k].append(1e9 * (time.perf_counter() - t0) / (10 * s.n_sub * ne))
    flops, top = FLOPS[drone.fem.elems.shape[1]], max(peak)
    out = {"precision": precision, "deviation_m": deviation, "bitwise": first is None, "peak_gflops": top,
           "kernel_speedup": float(np.median(np.array(kern["before"]) / np.array(kern["after"]))),
           "step_speedup": float(np.median(np.array(step["before"]) / np.array(step["after"])))}
    for k in sims:
        out[f"kernel_ns_{k}"] = float(np.median(kern[k]))
        out[f"step_ns_{k}"] = float(np.median(step[k]))
        out[f"peak_share_{k}"] = flops / min(kern[k]) / top
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--against", required=True, help="the earlier commit")
    p.add_argument("--drone", default="flower")
    p.add_argument("--rounds", type=int, default=100)
    p.add_argument("--blocks", type=int, default=60)
    a = p.parse_args(argv)
    drone = build_drone(conf.drone(a.drone), Path(native.default_cache_dir()), "quadratic")
    with tempfile.TemporaryDirectory() as folder:
        old = load_commit(a.against, Path(folder))
        for precision in ("float64", "float32"):
            r = compare(drone, old, precision, rounds=a.rounds, blocks=a.blocks)
            same = ("bitwise equal through 0.6 s" if r["bitwise"] else
                    f"positions {r['deviation_m']:.2g} m apart after 0.6 s")
            log.info(f"{a.drone} {precision}: kernel {r['kernel_ns_before']:.1f} -> {r['kernel_ns_after']:.1f} ns/element-substep "
                     f"(x{r['kernel_speedup']:.3f}; {r['peak_share_before']:.0%} -> {r['peak_share_after']:.0%} of the "
                     f"{r['peak_gflops']:.0f} GFLOP/s probe), step {r['step_ns_before']:.1f} -> {r['step_ns_after']:.1f} "
                     f"ns/element-substep (x{r['step_speedup']:.3f}); {same}")


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main()
