"""The skeleton every experiment's runner is handed: the typed config (converted once, at the
runner boundary, sdexp.eval.experiments.run_experiment), the experiment's params (its dataclass
in sdexp.experiment_params), the run folder, and where its tables and figures go.

A runner is ``run(run: Run) -> dict`` of metrics, named by ``experiment._target_`` in its
conf/experiment/<name>.yaml; optional beside it in its module: ``check(run)`` (its own input,
before anything is written) and ``summary(params, metrics) -> str`` (what the run prints last).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sdexp.cache import atomic_write
from sdexp.config import Config


@dataclass
class Run:
    cfg: Config       # the whole config, typed: cfg.drone, cfg.sim, ... are dataclasses
    out_dir: Path     # the run folder: tables, figures, metrics.json, config.yaml, cli.log

    @property
    def params(self) -> Any:
        """The experiment's params (its sdexp.experiment_params dataclass)."""
        return self.cfg.experiment.params

    def path(self, name: str) -> Path:
        """A file of the run folder."""
        return self.out_dir / name

    # written whole or not at all (a full disk mid-write leaves no short table, sdexp.cache.atomic_write)
    def table(self, frame, name: str, **to_csv) -> Path:
        """``<name>.csv`` in the run folder, without the frame's index."""
        path = self.path(f"{name}.csv")
        atomic_write(path, lambda tmp: frame.to_csv(tmp, index=False, **to_csv))
        return path

    def figure(self, fig, name: str, dpi: int = 120) -> Path:
        """``<name>.png`` in the run folder; the figure is closed."""
        from sdexp.figures import save_figure
        path = self.path(f"{name}.png")
        save_figure(fig, path, dpi)
        return path
