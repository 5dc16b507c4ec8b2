"""What a run says goes to the console and into its folder's cli.log (Python logging, no print);
progress bars stay off a console that is not a terminal."""
import os
import subprocess
import sys


def sdexp(*args, cwd, cache):
    return subprocess.run([sys.executable, "-m", "sdexp.cli", *args], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, "HYDRA_FULL_ERROR": "", "SDEXP_CACHE": str(cache)})


def test_a_runs_log_file_holds_what_the_run_said(tmp_path):
    cache = tmp_path / "cache"
    run = tmp_path / "run"
    res = sdexp("experiment=gallery", "experiment.params.drones=[rod]", "drone=rod", f"hydra.run.dir={run}",
                cwd=tmp_path, cache=cache)
    assert res.returncode == 0, res.stderr
    log = (run / "cli.log").read_text()
    for said in ("gallery (seed 0) on", "gallery done ->", "rod_elements: "):
        assert said in log and said in res.stdout, said
    assert "[sdexp.cli][INFO]" in log            # the file has time, module and level; the console plain lines
    assert not res.stdout.startswith("[")
    assert "gallery:" not in res.stderr          # no progress bar on a console that is not a terminal

    # a warning (a damaged mesh in the cache) goes to stderr and into the log file
    (mesh,) = cache.glob("mesh2d-*.npz")
    mesh.write_bytes(mesh.read_bytes()[:100])
    again = tmp_path / "again"
    res = sdexp("experiment=gallery", "experiment.params.drones=[rod]", "drone=rod", f"hydra.run.dir={again}",
                cwd=tmp_path, cache=cache)
    assert res.returncode == 0, res.stderr
    assert "is damaged" in res.stderr and "is damaged" not in res.stdout
    assert "[WARNING] - sdexp: cache entry" in (again / "cli.log").read_text()


def test_no_print_in_the_library():
    """The library speaks through logging (the CLI's one-line error to stderr aside)."""
    import re
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "sdexp"
    found = [f"{p.relative_to(root)}:{i}" for p in root.rglob("*.py")
             for i, line in enumerate(p.read_text().splitlines(), 1)
             if re.match(r"\s*print\(", line) and "file=sys.stderr" not in line]
    assert found == []


def test_the_log_says_which_fem_kernels_run(tmp_path, caplog):
    """The compiled C kernels announce themselves (INFO); the numba fallback warns instead
    (test_fem.py: test_without_a_compiler_the_numba_kernels_run)."""
    import logging

    from sdexp.sim.physics import native

    native.library.cache_clear()
    try:
        with caplog.at_level(logging.INFO, logger="sdexp.sim.physics.native"):
            assert native.library() is not None
        assert any("FEM kernels: compiled C" in r.getMessage() for r in caplog.records)
    finally:
        native.library.cache_clear()
