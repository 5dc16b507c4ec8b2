"""The only @hydra.main: resolve the output directory and hand over to a runner."""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from sdexp.config import register
from sdexp.errors import UserError

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
register()


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def _main(cfg: DictConfig) -> None:
    from sdexp.eval.experiments import run_experiment

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        metrics = run_experiment(cfg, out_dir)
    except UserError as err:
        print(f"sdexp: error: {err}", file=sys.stderr)
        sys.exit(2)
    print(f"sdexp: {cfg.experiment.name} done -> {out_dir}")
    for k, v in metrics.items():
        if not isinstance(v, (dict, list)):
            print(f"  {k}: {v}")


def main() -> None:
    _main()


if __name__ == "__main__":
    main()
