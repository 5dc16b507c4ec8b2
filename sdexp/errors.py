"""Errors that are the user's to fix: printed as one clear message, never as a traceback."""
from __future__ import annotations

# Every user error (sdexp's own checks, Hydra's config composition, an unwritable output folder)
# exits with this code; a traceback (a bug) exits with 1.
EXIT_USER_ERROR = 2

_NOISE = ("full_key:", "reference_type", "object_type", "See https://", "Set the environment variable",
          "Config search path", "provider=", "To append to your config use")


class UserError(Exception):
    """Bad input (config value, file, column): the message names it and the allowed range."""


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
