"""Experiment registry and the bookkeeping every run shares: validation, seeding, the saved
resolved config, an atomic metrics.json, and resuming (a job whose metrics.json exists skips)."""
from __future__ import annotations

import importlib
import json
import random
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from sdexp.cache import atomic_write
from sdexp.config import validate
from sdexp.errors import UserError

# name -> "module:function"; each function is run(cfg, out_dir) -> dict of metrics
RUNNERS = {
    "ablation_decomposition": "sdexp.eval.ablation_decomposition:run",
    "ablation_fixed_point": "sdexp.eval.ablation_fixed_point:run",
    "bench_control": "sdexp.eval.bench_control:run",
    "bench_sim": "sdexp.eval.bench_sim:run",
    "discrepancy": "sdexp.discrepancy.workflow:run",
    "discrepancy_bench": "sdexp.discrepancy.bench:run",
    "gallery": "sdexp.eval.gallery:run",
    "hover_deform": "sdexp.eval.hover_deform:run",
    "model_test": "sdexp.eval.model_test:run",
    "record": "sdexp.discrepancy.record:run",
    "nsweep": "sdexp.eval.nsweep:run",
    "obstacle": "sdexp.eval.obstacle:run",
    "sota": "sdexp.eval.sota:run",
    "validate_fem": "sdexp.eval.validate_fem:run",
}


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    try:
        import torch
        torch.manual_seed(seed)
    except ImportError:  # torch is only needed by the learning side
        pass


def write_json(path: Path, data: Any) -> None:
    atomic_write(path, lambda tmp: tmp.write_text(json.dumps(data, indent=2, default=float)))


def run_experiment(cfg: DictConfig, out_dir: Path) -> dict:
    name = cfg.experiment.name
    if name not in RUNNERS:
        raise UserError(f"experiment.name = {name!r} is unknown: choose one of {sorted(RUNNERS)}")
    validate(cfg)
    out_dir = Path(out_dir)
    done = out_dir / "metrics.json"
    if done.exists():
        print(f"sdexp: {done} exists, skipping (delete it to rerun)")
        return json.loads(done.read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    seed_everything(int(cfg.seed))
    module, func = RUNNERS[name].split(":")
    metrics = getattr(importlib.import_module(module), func)(cfg, out_dir)
    write_json(done, metrics)
    return metrics
