"""What every control experiment shares: the drone, its learned model, a flight with a progress
bar, the per-flight CSV, and the position-over-time figure of the paper's SOTA comparison."""
from __future__ import annotations

from pathlib import Path
import numpy as np
import pandas as pd

from sdexp.control.rollout import Flight, fly, metrics
from sdexp.control.tasks import Task
from sdexp.sim.simulator import Simulator


class Setup:
    """The drone, the learned model (cached data and networks) and simulators for cfg."""

    def __init__(self, cfg, progress: bool = True):
        from sdexp.eval.model_test import prepare
        from sdexp.sim.drone import build_drone

        self.cfg = cfg
        self.data, self.trained, self.dyn = prepare(cfg, progress)
        self.drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
        self.progress = progress

    def simulator(self) -> Simulator:
        """Every flight of an experiment sees the same noise stream (seed = cfg.seed)."""
        return Simulator(self.drone, self.cfg.sim, self.cfg.noise, seed=int(self.cfg.seed))

    def controller(self, name: str, sim: Simulator):
        from sdexp.eval import controllers
        return controllers.build(name, self.cfg, sim, self.dyn, self.data, self.trained, self.progress)

    def task(self, start, target, seconds: float, **kw) -> Task:
        return Task(start=start, target=target, seconds=seconds, n_s=self.dyn.n_s, **kw)

    def fly(self, sim: Simulator, controller, task: Task, label: str | None = None, watch=None
            ) -> tuple[Flight, dict]:
        """Fly with a progress bar; ``watch(sim)`` is called after every step (e.g. contacts).
        The loss-of-control limits are the config's ``flight`` group, the same for every controller."""
        bar = None
        if self.progress:
            from tqdm import tqdm
            bar = tqdm(total=int(round(task.seconds / sim.cfg.control_dt)), desc=f"fly {label or controller.name}",
                       unit="step", leave=False, disable=None)

        def on_step():
            if bar is not None:
                bar.update()
            if watch is not None:
                watch(sim)
        flight = fly(sim, controller, task, on_step=on_step, limits=getattr(self.cfg, "flight", None))
        if bar is not None:
            bar.close()
        return flight, metrics(flight, self.dyn.slices["p"], self.dyn.slices["e"], task.seconds)


def flight_table(flight: Flight, dyn) -> pd.DataFrame:
    """One row per control step: time, the noise-free state by channel, goal position, command."""
    a = flight.arrays()
    cols = {"t": a["t"]}
    names = {"s": [f"s_{i + 1}" for i in range(dyn.n_s)], "e": ["e_x", "e_y", "e_z"][: dyn.n_e] if dyn.n_e == 3 else ["theta"],
             "p": ["x", "y", "z"][: dyn.dim]}
    for blk in ("s", "e", "p"):
        for j, nm in enumerate(names[blk]):
            cols[nm] = a["x"][:, dyn.slices[blk]][:, j]
    for j, nm in enumerate(names["p"]):
        cols[f"goal_{nm}"] = a["goal"][:, dyn.slices["p"]][:, j]
    u = np.vstack([a["u"], np.full((1, dyn.m), np.nan)]) if len(a["u"]) else np.full((len(a["t"]), dyn.m), np.nan)
    for j in range(dyn.m):
        cols[f"u_{j + 1}"] = u[:, j]
    return pd.DataFrame(cols)


def position_plot(tables: dict[str, pd.DataFrame], titles: dict[str, str], path: Path, suptitle: str) -> None:
    """The paper's SOTA figure: (x, y, z) over time, one panel per flight, goal dashed."""
    from sdexp.figures import pyplot
    plt = pyplot()

    n = len(tables)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.6), squeeze=False)
    for ax, (name, tab) in zip(axes[0], tables.items()):
        for axis, color in zip(("x", "y", "z"), ("tab:red", "tab:green", "tab:blue")):
            if axis in tab:
                ax.plot(tab["t"], tab[axis], color=color, label=axis)
                ax.plot(tab["t"], tab[f"goal_{axis}"], color=color, ls="--", lw=0.8)
        ax.set_title(titles.get(name, name), fontsize=9)
        ax.set_xlabel("t (s)")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("position (m); dashed: goal")
    axes[0, 0].legend(loc="best", fontsize=8)
    fig.suptitle(suptitle)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
