"""The Stable-Baselines3 example (examples/train_sb3.py) runs a few hundred steps and compares
its agent with ours in the same environment; skipped without the rl extra."""
import importlib.util
from pathlib import Path

import pytest

from tests.eval.references import SHRUNK

pytest.importorskip("stable_baselines3", reason="the rl extra: pip install -e '.[rl]'")

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "train_sb3.py"


def test_the_sb3_example_trains_and_compares_with_ours(cache_dir):
    spec = importlib.util.spec_from_file_location("train_sb3", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    overrides = [a for o in [*SHRUNK[1:], f"cache_dir={cache_dir}"] for a in ("--override", o)]
    out = example.main(["--steps", "256", "--n-steps", "128", "--seconds", "0.5", "--episodes", "2",
                        "--compare-ours", *overrides])
    steps = 50   # 0.5 s at 100 Hz; the reward is in (0, 1] per step
    # ours on this 800-transition rod model may find no stabilising gain at once (a controller
    # failure, return 0: the nets differ in rounding with the torch threads earlier tests left)
    assert out["steps"] == 256 and 0 < out["ppo_return"] <= steps and 0 <= out["ours_return"] <= steps
