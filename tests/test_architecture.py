"""The architecture as a rule: the import-linter contracts of pyproject.toml (a top-down stack of
packages, no import cycles, the learning side seeing the drone through sdexp.sensing only)."""
import os
import subprocess
import sys
from pathlib import Path

import importlinter  # noqa: F401  (a test extra: a missing linter fails here, it does not skip)

ROOT = Path(__file__).resolve().parents[1]


def test_import_contracts_hold():
    # lint-imports of this interpreter on this checkout, not on an installed copy elsewhere
    run = subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
                          "sys.exit(lint_imports_command())", "--no-cache"], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.returncode == 0, run.stdout + run.stderr


def test_one_place_picks_the_matplotlib_backend():
    root = ROOT / "sdexp"
    found = [str(p.relative_to(root)) for p in root.rglob("*.py") if "matplotlib.use(" in p.read_text()]
    assert found == ["figures.py"]


def test_an_experiment_is_found_by_its_name():
    """conf/experiment/<name>.yaml runs sdexp/eval/<name>.py's run, for every experiment; one that
    trains in the Gymnasium environments sits beside them, sdexp/envs/<name>.py (the layers put
    sdexp.envs above sdexp.eval)."""
    from sdexp import conf
    wrong = {n: conf.read("experiment", n).experiment._target_ for n in conf.names("experiment")
             if conf.read("experiment", n).experiment._target_ not in (f"sdexp.eval.{n}.run", f"sdexp.envs.{n}.run")}
    assert not wrong, wrong
