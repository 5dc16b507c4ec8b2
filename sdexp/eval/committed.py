"""Reading committed result folders strictly, for ``python -m sdexp.eval.paper_report``.

A verdict must never change because a file was damaged: a truncated config.yaml that loses its
``sim.element`` would otherwise read as a linear-element run and drop out, and a seed folder
without metrics.json would silently shrink "5 of 5" to "4 of 4". So every file the report
depends on is read here whole or refused with a UserError naming it (the report then writes
nothing), and a metric or parameter the report needs but the file lacks names the file too.
"""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import yaml

from sdexp.errors import UserError

FIX = "rerun that run, restore the file (git checkout results/), or move the folder out of results/"


class Record(dict):
    """A metrics.json or config.yaml mapping whose missing keys are a UserError naming the file
    (a KeyError would be a traceback without it); nested mappings alike."""

    def __init__(self, data: dict, source: Path, prefix: str = ""):
        super().__init__({k: Record(v, source, f"{prefix}{k}.") if isinstance(v, dict) else v
                          for k, v in data.items()})
        self.source, self.prefix = source, prefix

    def __missing__(self, key):
        raise UserError(f"{self.source} has no {self.prefix}{key}, which the report needs: {FIX}")


@dataclass
class Run:
    folder: Path
    metrics: Record
    config: Record

    @property
    def seed(self) -> int:
        return int(self.config.get("seed", 0))

    @property
    def started(self) -> str | None:
        """When the run started ("YYYY-MM-DD HH:MM:SS", UTC, its cli.log's first line), or None
        where its log has none (runs from before the log kept timestamps)."""
        log = self.folder / "cli.log"
        try:
            with open(log) as fh:
                first = fh.readline()
        except (OSError, UnicodeDecodeError):
            return None
        return first[1:20] if first.startswith("[") and len(first) > 20 else None


def _text(path: Path) -> str:
    if not path.is_file():
        raise UserError(f"{path} is missing: a committed run folder needs its metrics.json and config.yaml; {FIX}")
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"{path} cannot be read ({err}): {FIX}") from None


def _metrics(path: Path) -> Record:
    try:
        data = json.loads(_text(path))
    except ValueError as err:
        raise UserError(f"{path} is not valid JSON ({err}; truncated?): {FIX}") from None
    if not isinstance(data, dict):
        raise UserError(f"{path} is not a mapping of metrics: {FIX}")
    return Record(data, path)


def _config(path: Path, name: str) -> Record:
    text = _text(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise UserError(f"{path} is not valid YAML ({' '.join(str(err).split())}): {FIX}") from None
    # sdexp writes a config whole, ending in a newline and with the experiment last: a file cut
    # short can still parse (a value cut mid-line, the last sections gone)
    if not isinstance(data, dict) or not text.endswith("\n") or "sim" not in data or "experiment" not in data:
        raise UserError(f"{path} is truncated (it lacks the sim or experiment section, or its last line): {FIX}")
    ran = (data.get("experiment") or {}).get("name", name)
    if ran != name:
        raise UserError(f"{path} is a run of {ran}, not of {name}: {FIX}")
    return Record(data, path)


def check_csv(path: Path) -> None:
    """A table of a committed run is whole: not empty, its last line ended, every row as wide as
    its header (a write cut short by a full disk or a copy leaves a short last row)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"{path} cannot be read ({err}): {FIX}") from None
    if not text.strip() or not text.endswith("\n"):
        raise UserError(f"{path} is {'empty' if not text.strip() else 'truncated (its last line is cut)'}: {FIX}")
    rows = csv.reader(text.splitlines())
    width = len(next(rows))
    for i, row in enumerate(rows, start=2):
        if len(row) != width:
            raise UserError(f"{path}: line {i} has {len(row)} fields, its header {width} (truncated or damaged): {FIX}")


def load(folder: Path, name: str) -> Run:
    """One committed run of experiment ``name``: its metrics, its config and its tables, checked."""
    run = Run(folder, _metrics(folder / "metrics.json"), _config(folder / "config.yaml", name))
    for table in sorted(folder.glob("*.csv")):
        check_csv(table)
    return run


def folders(results: Path, name: str) -> list[Path]:
    """``<results>/<name>`` and every job folder of ``<results>/<name>_seeds``: each must hold a
    run (a folder without its files is an error, not a smaller count)."""
    seeds = results / f"{name}_seeds"
    jobs = sorted(p for p in seeds.iterdir() if p.is_dir() and not p.name.startswith(".")) if seeds.is_dir() else []
    return ([results / name] if (results / name).exists() else []) + jobs


def check_results_dir(results: Path) -> None:
    if not results.exists():
        raise UserError(f"results folder {results} does not exist: give the folder of committed runs "
                        f"(python -m sdexp.eval.paper_report [results_dir], default results/)")
    if not results.is_dir():
        raise UserError(f"results folder {results} is not a folder: give the folder of committed runs "
                        f"(python -m sdexp.eval.paper_report [results_dir], default results/)")
