"""What every control experiment shares: the drone, its learned model, a flight with a progress
bar (or log lines), the per-flight CSV, and the position-over-time figure of the paper's SOTA comparison."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.control.rollout import Flight, fly, metrics
from sdexp.control.tasks import Task
from sdexp.sim.simulator import Simulator


@dataclass(frozen=True)
class StateLayout:
    """The decomposed state's sizes and blocks (what a flight's record and metrics read), known
    from the drone alone: a flight of a controller without a learned model needs no training."""
    n_s: int
    n_e: int
    dim: int
    m: int

    @property
    def slices(self) -> dict[str, slice]:
        from sdexp.model.dynamics import state_slices
        return state_slices(self.n_s, self.n_e, self.dim, self.m)


class Setup:
    """The drone, the learned model (cached data and networks, identified when first asked for:
    ``data``, ``trained``, ``dyn``) and simulators for cfg."""

    def __init__(self, cfg, progress: bool = True):
        from sdexp.sim.drone import build_drone

        self.cfg = cfg
        self.drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
        self.progress = progress
        self._learned = None
        lay = self.drone.layout
        self.layout = StateLayout(lay.n_s, 3 if lay.dim == 3 else 1, lay.dim, self.drone.num_rotors)

    def _identified(self):
        if self._learned is None:
            from sdexp.eval.learning import learned_model
            self._learned = learned_model(self.cfg, self.drone, self.progress)
        return self._learned

    data = property(lambda self: self._identified()[0])
    trained = property(lambda self: self._identified()[1])
    dyn = property(lambda self: self._identified()[2])

    def simulator(self) -> Simulator:
        """Every flight of an experiment sees the same noise stream (seed = cfg.seed)."""
        return Simulator(self.drone, self.cfg.sim, self.cfg.noise, seed=int(self.cfg.seed))

    def controller(self, name: str, sim: Simulator):
        from sdexp.eval import controllers
        if name not in controllers.LEARNED:   # the rigid and privileged baselines: no training
            return controllers.build(name, self.cfg, sim, progress=self.progress)
        return controllers.build(name, self.cfg, sim, self.dyn, self.data, self.trained, self.progress)

    def task(self, start, target, seconds: float, **kw) -> Task:
        return Task(start=start, target=target, seconds=seconds, n_s=self.layout.n_s, **kw)

    def fly(self, sim: Simulator, controller, task: Task, label: str | None = None, watch=None,
            recorder=None) -> tuple[Flight, dict]:
        """Fly as a logged phase (a progress bar on a terminal, sdexp.log.Phase); ``watch(sim)`` is
        called after every step (e.g. contacts).
        The loss-of-control limits are the config's ``flight`` group, the same for every controller.
        ``recorder``: a ``FrameRecorder`` that keeps the frames of an animation (``animate``)."""
        from sdexp.log import Phase
        steps = int(round(task.seconds / sim.cfg.control_dt))
        bar = Phase(f"flight {label or controller.name}, {task.seconds:g} s", total=steps, unit="steps",
                    enabled=self.progress)

        def on_step():
            bar.update()
            if watch is not None:
                watch(sim)
        with bar:
            flight = fly(sim, controller, task, on_step=on_step, limits=self.cfg.flight, recorder=recorder)
            flown = flight.t[-1]
            ended = f"failed: {flight.failure}" if flight.failure else "survived"
            bar.close(f"{flown:.2f} s flown ({ended}), {flown / max(bar.elapsed, 1e-9):.2f}x real time")
        return flight, metrics(flight, self.layout.slices["p"], self.layout.slices["e"], task.seconds)

    def recorder(self, on: bool):
        """A ``FrameRecorder`` for a flight to animate (None: ``on`` is false)."""
        from sdexp.control.rollout import FrameRecorder
        from sdexp.eval.animation import FRAME_RATE
        return FrameRecorder(FRAME_RATE) if on else None

    def animate(self, out_dir: Path, stem: str, recorder, title: str) -> None:
        """``<stem>.mp4`` of a recorded flight, and with ``experiment.params.paraview`` the
        ParaView series ``<stem>_vtu/``."""
        if recorder is None:
            return
        from sdexp.eval.animation import save_flight
        save_flight(out_dir, stem, recorder, self.drone, list(self.cfg.sim.obstacles), title, self.progress,
                    paraview=bool(getattr(self.cfg.experiment.params, "paraview", False)))


def ending(m: dict) -> str:
    """How a flight ended, for a figure title: survived, or the failure's time and short reason."""
    if m["survived"]:
        return f"survived {m['survival_time']:.0f} s"
    return f"failed at {m['survival_time']:.2f} s ({short_reason(m['failure'])})"


def short_reason(failure: str) -> str:
    """A flight's failure without its kind and numbers: "tilt 93.1 deg", "left the arena"."""
    why = str(failure).split(": ", 1)[-1]
    return why.split(",")[0] if why.startswith("left the arena") else why.split(" > ")[0]


def flight_table(flight: Flight, layout) -> pd.DataFrame:
    """One row per control step: time, the noise-free state by channel, goal position, command
    (``layout``: a StateLayout or the LearnedDynamics, whose blocks it shares)."""
    a = flight.arrays()
    cols = {"t": a["t"]}
    names = {"s": [f"s_{i + 1}" for i in range(layout.n_s)], "e": ["e_x", "e_y", "e_z"][: layout.n_e] if layout.n_e == 3 else ["theta"],
             "p": ["x", "y", "z"][: layout.dim]}
    for blk in ("s", "e", "p"):
        for j, nm in enumerate(names[blk]):
            cols[nm] = a["x"][:, layout.slices[blk]][:, j]
    for j, nm in enumerate(names["p"]):
        cols[f"goal_{nm}"] = a["goal"][:, layout.slices["p"]][:, j]
    u = np.vstack([a["u"], np.full((1, layout.m), np.nan)]) if len(a["u"]) else np.full((len(a["t"]), layout.m), np.nan)
    for j in range(layout.m):
        cols[f"u_{j + 1}"] = u[:, j]
    return pd.DataFrame(cols)


def position_plot(tables: dict[str, pd.DataFrame], titles: dict[str, str], path: Path, suptitle: str,
                  seconds: float) -> None:
    """The paper's SOTA figure: (x, y, z) over time, one panel per flight, goal dashed. Panels
    share the task's whole time and one position scale (start and goal +-3 m; a flight that leaves it
    runs off the panel), so a flight that ended early reads as a short line ending in a cross."""
    from matplotlib.lines import Line2D

    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    n = len(tables)
    cols = 2 if n > 2 else n
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.6 * cols, 3.6 * rows + 0.9), sharex=True, sharey=True,
                             squeeze=False)
    goals = np.concatenate([np.r_[tab[[f"goal_{a}" for a in "xyz" if f"goal_{a}" in tab]].to_numpy().ravel(),
                                  tab[[a for a in "xyz" if a in tab]].iloc[0].to_numpy()]   # and the start
                            for tab in tables.values()])
    colors = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
    for ax, (name, tab) in zip(axes.ravel(), tables.items()):
        for axis, color in colors.items():
            if axis in tab:
                ax.plot(tab["t"], tab[axis], color=color, lw=1.8)
                ax.plot(tab["t"], tab[f"goal_{axis}"], color=color, ls="--", lw=1.0)
                if tab["t"].iloc[-1] < seconds - 0.05:
                    ax.plot(tab["t"].iloc[-1], np.clip(tab[axis].iloc[-1], goals.min() - 3, goals.max() + 3),
                            "x", color=color, ms=10, mew=2.5)
        ax.set_title(titles.get(name, name), fontsize=11)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=10)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    axes[0, 0].set_xlim(0, seconds)
    axes[0, 0].set_ylim(goals.min() - 3, goals.max() + 3)
    for ax in axes[-1]:
        ax.set_xlabel("t (s)", fontsize=11)
    for ax in axes[:, 0]:
        ax.set_ylabel("position (m)", fontsize=11)
    handles = [Line2D([], [], color=c, lw=1.8, label=a) for a, c in colors.items()]
    handles += [Line2D([], [], color="gray", ls="--", label="goal"),
                Line2D([], [], color="gray", marker="x", ls="", ms=9, mew=2.5, label="flight ended (failure)")]
    fig.legend(handles=handles, loc="upper right", ncol=5, fontsize=10, frameon=False)
    fig.suptitle(suptitle, x=0.02, ha="left", fontsize=13)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    save_figure(fig, path, dpi=110)
