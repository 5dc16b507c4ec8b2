import os
from pathlib import Path

import pytest

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
