"""experiment=kernel_spread: one fleet per BLAS kernel choice, each in its own process and cache
(its data and nets made afresh under that kernel, the meshes shared), gathered in one table."""
import pandas as pd
import pytest

from sdexp.errors import UserError
from sdexp.eval.run import run_experiment
from tests.conftest import make_cfg
from tests.eval.references import REDUCED, SHRUNK

FLEET = [*SHRUNK[1:], *REDUCED["fleet"], "experiment.params.drones=[rod]", "experiment.params.tasks=[hover]",
         "experiment.params.controllers=[ours]"]


def overrides(items):
    return "experiment.params.overrides=[" + ",".join(f"'{o}'" for o in items) + "]"


def test_each_kernel_choice_learns_afresh_in_its_own_process(tmp_path, cache_dir):
    cfg = make_cfg("experiment=kernel_spread", f"cache_dir={cache_dir}", overrides(FLEET),
                   "experiment.params.kernels=[haswell]")
    metrics = run_experiment(cfg, tmp_path)
    table = pd.read_csv(tmp_path / "kernel_spread.csv")
    assert list(table["kernel"]) == ["haswell"] and (table["task"] == "hover").all()
    # the environment reached the process: OpenBLAS ran the kernel asked for
    assert table.set_index("kernel").loc["haswell", "openblas"].lower() == "haswell"
    assert metrics["rod_seed0_hover_ours_kernels"] == 1 and metrics["kernels_failed"] == 0
    for kernel in ("haswell",):
        entries = list((tmp_path / "caches" / kernel).iterdir())
        made = {e.name.split("-")[0] for e in entries if not e.is_symlink()}
        shared = {e.name.split("-")[0] for e in entries if e.is_symlink()}
        assert "data" in made and "nets" in made and "data" not in shared
        assert (tmp_path / "fleets" / kernel / "fleet.csv").exists()
    assert (tmp_path / "kernel_spread.png").exists()


@pytest.mark.parametrize("args, words", [
    ([overrides(["experiment.params.drones=[rodd]"])], ["experiment.params.drones", "rodd"]),
    ([overrides(["model.epoks=3"])], ["experiment.params.overrides", "model.epoks"]),
    (["experiment.params.kernels=[skylake]"], ["experiment.params.kernels", "haswell_mkl_avx2"]),
    (["experiment.params.kernels=[]"], ["experiment.params.kernels", "non-empty"]),
    (["experiment.params.shared=[data]"], ["experiment.params.shared", "mesh2d"]),
])
def test_bad_params_are_refused_by_name_before_any_fleet_starts(tmp_path, args, words):
    with pytest.raises(UserError) as err:
        run_experiment(make_cfg("experiment=kernel_spread", *args), tmp_path)
    for w in words:
        assert w in str(err.value), str(err.value)
    assert not (tmp_path / "fleets").exists()
