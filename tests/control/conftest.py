import contextlib

import pytest

try:
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    threadpool_limits = None


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """The control loops call SciPy's Riccati solver hundreds of times on 6x6 matrices; with
    two OpenBLAS threads on a busy 2-core machine each call takes ~20 ms instead of ~1.5 ms."""
    with (threadpool_limits(1) if threadpool_limits is not None else contextlib.nullcontext()):
        yield
