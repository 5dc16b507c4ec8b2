"""The compiled step is bitwise the step every committed result was computed with (issue 25).

kernels.c's SIMD vertex loops (kick, drift) and gathered node offsets replaced scalar loops; a
result repeats to the digit only if the new step rounds exactly as the old one did (chaotic
flights amplify one ulp). These tests build BASE's kernels.c and load its integrator.py beside
this tree's (sdexp.eval.bench_kernels.load_commit, today's compiler flags) and step both alike:
positions and velocities must stay np.array_equal after every control step, in float64 and
float32, on 1 and 2 threads, with and without ground and box contacts, on a 2D and a 3D drone,
and on blocks with pinned vertices and added inertia."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numba
import numpy as np
import pytest

from sdexp import conf
from sdexp.config import BoxConfig
from sdexp.sim.physics import native
from sdexp.sim.physics.integrator import Body

from .test_fem import spun_block

BASE = "5babb13"   # the last commit with the scalar vertex loops (issue 25's base)
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def old(tmp_path_factory):
    """(Body class, compiled library) of BASE; skipped where its source or a compiler is missing."""
    if shutil.which("git") is None or native.library() is None:
        pytest.skip("needs git and a C compiler")
    if subprocess.run(["git", "cat-file", "-e", f"{BASE}^{{commit}}"], cwd=ROOT, capture_output=True).returncode:
        pytest.skip(f"commit {BASE} is not in this checkout")
    from sdexp.eval.bench_kernels import load_commit
    return load_commit(BASE, tmp_path_factory.mktemp("base"))


def _contacts(drone, contact: str) -> dict:
    rest = drone.fem.rest
    if contact == "ground":   # 2 cm below the lowest vertex: reached once the drone sinks
        return {"ground": float(rest[:, 1].min()) - 0.02}
    if contact == "boxes":    # a box over half the drone's span, its top 2 cm above the lowest vertex
        lo, hi = list(rest.min(0)), list(rest.max(0))
        lo[0] = (lo[0] + hi[0]) / 2
        hi[0] += 1.0
        hi[1] = lo[1] + 0.02
        lo[1] -= 1.0
        return {"obstacles": [BoxConfig(min=lo, max=hi)]}
    return {}


@pytest.mark.parametrize("contact", ["none", "ground", "boxes"])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("name,steps", [("rod", 200), ("flower", 40)])
def test_flights_step_bitwise_as_the_base_commit(old, name, steps, precision, threads, contact):
    """A 2D and a 3D drone (quadratic elements, deformation damping), noise-free, under random
    thrust holds: every control step's positions and velocities bitwise those of BASE's step."""
    from sdexp.eval.bench_kernels import first_difference
    from sdexp.sim.drone import build_drone

    drone = build_drone(conf.drone(name), Path(native.default_cache_dir()), "quadratic")
    sim = _contacts(drone, contact)
    first, deviation, lowest = first_difference(drone, old, precision, steps, threads=threads, **sim)
    assert first is None, f"apart from control step {first} on (positions {deviation:.3g} m apart at the end)"
    if contact == "ground":
        assert lowest == sim["ground"], "the flight never reached the ground"


@pytest.mark.parametrize("deform_damping", [0.0, 20.0])
@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("threads", [1, 2])
def test_pinned_blocks_step_bitwise_as_the_base_commit(old, dim, threads, order, deform_damping):
    """test_fem's spun block (pinned vertices, a rotor, gravity, added inertia on every fifth
    vertex), linear and quadratic, with and without deformation damping, free and on a ground
    with friction:
    bitwise BASE's step."""
    old_body, old_lib = old
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    fem, rotors, v0, added, pinned = spun_block(dim, order)
    for ground in (None, -0.201):   # 1 mm under the block
        bodies = [cls(fem, threads, rotors, ground=ground, friction=0.5, pinned=pinned, added_mass=added)
                  for cls in (old_body, Body)]
        bodies[0]._lib = old_lib
        for body in bodies:
            body.v[:] = v0
            body.v[pinned] = 0.0
        for _ in range(20):
            out = [body.run(10 * order, 2e-4 / order, [3.0], 0.5, 9.81, deform_damping) for body in bodies]
            assert out[0] == out[1]
        for a in ("x", "v", "q"):
            np.testing.assert_array_equal(getattr(bodies[0], a), getattr(bodies[1], a))
