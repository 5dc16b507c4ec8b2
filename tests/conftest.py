import os

import pytest


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """One mesh cache per test session, outside the user's cache."""
    path = tmp_path_factory.mktemp("sdexp-cache")
    os.environ["SDEXP_CACHE"] = str(path)
    return str(path)
