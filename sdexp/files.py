"""Files written whole or not at all: a killed run or a full disk never leaves a half-written file
under its final name (cache entries, tables, figures, metrics.json, REPORT.md)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp_path)`` then rename tmp_path to ``path`` (atomic on one filesystem)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except OSError as err:
        err.filename = str(path)   # the file the caller wrote, not its temporary name
        raise
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
