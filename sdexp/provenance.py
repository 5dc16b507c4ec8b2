"""Which code made a result: sdexp's version and, in a git checkout, its commit (and whether the
tracked files had uncommitted changes). A committed result is only reproducible at the code
that made it: ours' SOTA flight, a closed loop through noise, ends 0.14 or 0.32 m from its
target depending on the last bits of the force kernels' arithmetic."""
from __future__ import annotations

import subprocess
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


@lru_cache(maxsize=1)
def source() -> str:
    """'sdexp 0.1.0, commit 1a2b3c4d5e6f' (+ ', with uncommitted changes'); the version alone
    outside a git checkout or where git is missing."""
    try:
        out = f"sdexp {version('sdexp')}"
    except PackageNotFoundError:
        out = "sdexp (not installed)"
    root = Path(__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
    try:
        commit = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".")
    except (OSError, subprocess.SubprocessError):
        return out
    return f"{out}, commit {commit}" + (", with uncommitted changes" if dirty else "")
