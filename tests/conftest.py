import os
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

from sdexp.eval.run import typed

# the sdexp processes the tests start run this checkout's code, not whichever one is installed
# (an editable install of another worktree would otherwise be tested in their place)
_ROOT = str(Path(__file__).resolve().parents[1])
os.environ["PYTHONPATH"] = os.pathsep.join([_ROOT, *filter(None, [os.environ.get("PYTHONPATH")])])


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """One mesh cache per test session, outside the user's cache."""
    path = tmp_path_factory.mktemp("sdexp-cache")
    os.environ["SDEXP_CACHE"] = str(path)
    return str(path)


def make_cfg(*overrides, hydra: bool = False):
    """The composed config, as the cli hands it to run_experiment (``hydra``: with the hydra
    node, e.g. for the launcher's settings). The one place the tests compose a config."""
    with initialize_config_module(config_module="sdexp.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides), return_hydra_config=hydra)


def make_config(*overrides):
    """The typed config (sdexp.config.Config), as a runner and everything below it sees it."""
    return typed(make_cfg(*overrides))
