"""What a run says goes to the console and into its folder's cli.log (Python logging, no print);
progress bars stay off a console that is not a terminal."""
import os
import subprocess
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]


def sdexp(*args, cwd, cache):
    # PYTHONPATH: this checkout's sdexp, not whichever one is installed
    return subprocess.run([sys.executable, "-m", "sdexp.cli", *args], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, "HYDRA_FULL_ERROR": "", "SDEXP_CACHE": str(cache), "PYTHONPATH": str(ROOT)})


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


def test_a_redirected_cold_run_logs_every_long_phase_with_its_time(tmp_path):
    """Output redirected (not a terminal), nothing cached: meshing, data generation, each net's
    training, the neural controller's training and each flight log their start and their end with
    the time taken and a rate, on the console and in cli.log."""
    import re

    from tests.eval.references import reduced_overrides
    run = tmp_path / "run"
    res = sdexp(*reduced_overrides("sota", str(tmp_path / "cache")), f"hydra.run.dir={run}", cwd=tmp_path,
                cache=tmp_path / "cache")
    assert res.returncode == 0, res.stderr
    log = (run / "cli.log").read_text()
    phases = ["meshing rod", "data generation rod", "training net d", "training net g", "training net h",
              "training neural controller", "flight ours", "flight LQR (rest shape)",
              "flight geometry-updating LQR", "flight neural controller"]
    for phase in phases:
        for text in (res.stdout, log):
            assert f"sdexp: {phase}" in text and re.search(rf"{re.escape(phase)}[^\n]*: started", text), phase
            assert re.search(rf"{re.escape(phase)}[^\n]*: done in \d+\.\d s", text), phase
    assert re.search(r"data generation rod[^\n]*: done in [^\n]* [\d,.]+ samples/s", log)
    assert re.search(r"flight ours[^\n]*: done in [^\n]* steps/s; 0\.30 s flown \(survived\)", log)
    assert "\r" not in res.stderr and "it/s" not in res.stderr    # no progress bar off a terminal


def phase_lines(caplog, **kw):
    """The lines of a Phase run on a fake clock (1 s per update unless ``step``)."""
    import logging

    from sdexp.log import Phase
    now = [0.0]
    step = kw.pop("step", 1.0)
    updates = kw.pop("updates")
    with caplog.at_level(logging.INFO, logger="sdexp.progress"):
        phase = Phase("job", clock=lambda: now[0], **{"bar": False, "heartbeat": False, **kw})
        for _ in range(updates):
            now[0] += step
            phase.update()
        phase.close()
    return [r.getMessage() for r in caplog.records]


def test_progress_lines_come_every_tenth_but_not_within_seconds(caplog):
    from sdexp import log
    lines = phase_lines(caplog, total=100, unit="steps", updates=100)
    assert lines[0] == "sdexp: job: started (100 steps)"
    assert lines[-1] == "sdexp: job: done in 100.0 s, 1 steps/s"
    middle = lines[1:-1]
    assert [m.split(": ")[2].split("%")[0] for m in middle] == [str(p) for p in range(10, 100, 10)]
    assert "10% (10/100 steps), 10.0 s so far, 1 steps/s, about 90.0 s left" in middle[0]
    caplog.clear()
    # a phase of a few seconds: start and end only
    assert len(phase_lines(caplog, total=100, unit="steps", updates=100, step=log.MIN_INTERVAL / 100)) == 2


def test_a_phase_without_total_beats_and_an_aborted_one_says_so(caplog):
    import logging
    import time

    from sdexp import log
    saved = log.MAX_INTERVAL
    log.MAX_INTERVAL = 0.2
    try:
        with caplog.at_level(logging.INFO, logger="sdexp.progress"):
            try:
                with log.Phase("meshing", bar=False):
                    time.sleep(1.5)
                    raise ValueError("boom")
            except ValueError:
                pass
    finally:
        log.MAX_INTERVAL = saved
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "sdexp: meshing: started" and lines[-1].startswith("sdexp: meshing: stopped after 1.")
    assert any(line.endswith("s so far") for line in lines[1:-1])    # the heartbeat
    time.sleep(1.2)
    assert len(caplog.records) == len(lines)                          # and it stopped with the phase


def test_on_a_terminal_the_bar_replaces_the_progress_lines(caplog):
    lines = phase_lines(caplog, total=100, unit="steps", updates=100, bar=True)
    assert len(lines) == 2 and lines[1].startswith("sdexp: job: done in")


def test_a_quiet_phase_says_nothing_when_quick_and_all_when_slow(caplog):
    """A compile the caches usually spare: silent in the usual case, said once it is slow."""
    import logging
    import time

    from sdexp.log import Phase
    with caplog.at_level(logging.INFO, logger="sdexp.progress"):
        with Phase("compiling", quiet_for=0.3, bar=False):
            pass
        assert caplog.records == []
        with Phase("compiling", quiet_for=0.3, bar=False):
            time.sleep(1.3)   # the heartbeat looks every second
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and lines[0].startswith("sdexp: compiling: started 1.") and lines[0].endswith(" s ago")
    assert lines[1].startswith("sdexp: compiling: done in 1.")


def test_numba_compiling_is_said_when_it_takes_long(caplog):
    """A run of compiles (none a pause apart) is one quiet phase naming the function the run
    called; and the listener is on numba's own compile events."""
    import logging
    import time

    import numba

    from sdexp import log
    with caplog.at_level(logging.INFO, logger="sdexp.progress"):
        compiles = log.NumbaCompiles(quiet=0.5, pause=0.3)
        compiles.on_start("sdexp.quick")
        compiles.on_end()
        time.sleep(0.6)
        assert caplog.records == [] and compiles.phase is None      # quick: nothing said
        compiles.on_start("sdexp.sim.slow")
        time.sleep(1.2)
        compiles.on_start("sdexp.sim.callee")                       # compiled inside the first
        compiles.on_end()
        compiles.on_end()
        time.sleep(0.6)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2, lines
    assert lines[0].startswith("sdexp: numba: compiling on first use") and lines[0].endswith("now sdexp.sim.slow")
    assert "done in 1." in lines[1] and "functions/s" in lines[1]
    log.say_numba_compiles()
    numba.njit(lambda x: x + 1)(1)   # not cached: compiled, which starts a run of compiles
    assert log._numba_said.phase is not None
