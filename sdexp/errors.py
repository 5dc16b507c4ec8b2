"""Errors that are the user's to fix: printed as one clear message, never as a traceback."""
from __future__ import annotations

import errno
import shutil
from pathlib import Path

# Every user error (sdexp's own checks, Hydra's config composition, an unwritable output folder)
# exits with this code; a traceback (a bug) exits with 1.
EXIT_USER_ERROR = 2

_NOISE = ("full_key:", "reference_type", "object_type", "See https://", "Set the environment variable",
          "Config search path", "provider=", "To append to your config use")


class UserError(Exception):
    """Bad input (config value, file, column): the message names it and the allowed range."""


def did_you_mean(name: str, choices, prefix: str = "") -> str:
    """" (did you mean <prefix><closest>?)" for a misspelled ``name`` among ``choices``, else ""."""
    import difflib
    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1)
    return f" (did you mean {prefix}{close[0]}?)" if close else ""


def one_line(err: BaseException) -> str:
    """An exception and its causes as one line, without the hints that mislead (Hydra's
    "To append to your config use +key=..." turns a typo into a silent new key)."""
    parts: list[str] = []
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        lines = [ln.strip() for ln in str(err).splitlines()]
        text = " ".join(ln for ln in lines if ln and not ln.startswith(_NOISE))
        if text and text != "None" and "$VALUE" not in text and not any(text in p for p in parts):
            parts.append(text.rstrip("."))
        err = err.__cause__
    return ": ".join(parts) or "unknown error"


# a disk or quota that is full, a file system that turned read-only: the machine's state, which the
# user fixes; one line naming the path, not a traceback
FULL = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


def disk_full(err: OSError, where: str | Path, alternative: str) -> UserError | None:
    """``err`` as a UserError naming the file (else ``where``) and the space left there, if it is
    a full disk or quota; None for any other OSError. ``alternative``: how to write elsewhere."""
    if err.errno not in FULL:
        return None
    path = Path(err.filename or where)
    free = next((shutil.disk_usage(p).free for p in (path, *path.parents) if p.exists()), None)
    left = f", {free / 1e6:.1f} MB free there" if free is not None else ""
    return UserError(f"cannot write {path}: {err.strerror or 'no space left on device'}{left}: free some space"
                     + (f", {alternative}" if alternative else ""))
