"""Logging helpers. The run's handlers are configured by Hydra from conf/hydra/job_logging/sdexp.yaml:
INFO to stdout, warnings and errors to stderr, everything to the run folder's cli.log."""
from __future__ import annotations

import logging


class BelowWarning(logging.Filter):
    """Lets through the records below WARNING (those go to stderr instead)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING


def to_log_files(message: str, level: int = logging.ERROR, name: str = "sdexp") -> None:
    """``message`` into the log files only (the console has it already, e.g. a one-line error)."""
    record = logging.LogRecord(name, level, __file__, 0, message, None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)
