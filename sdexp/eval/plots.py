"""Plots every experiment leaves behind, readable at a glance."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402


def refinement_plot(table: pd.DataFrame, path: Path) -> None:
    """Cantilever error against elements through the thickness, 2D and 3D, per element type
    (linear dashed, quadratic solid)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    markers = {"structured 2D": "o", "structured 3D": "s", "pytetwild 3D": "^"}
    for (element, mesh), group in table.groupby(["element", "mesh"], sort=False):
        x = group["thickness_over_edge"]
        for ax, col in zip(axes, ("sag_error", "freq_error")):
            ax.plot(x, 100 * group[col], marker=markers.get(mesh, "o"), ls="-" if element == "quadratic" else "--",
                    label=f"{element}, {mesh}")
    for ax, title in zip(axes, ("static tip sag vs Euler-Bernoulli", "1st bending frequency vs Euler-Bernoulli")):
        ax.axhline(0, color="k", lw=0.8)
        ax.axhspan(-10, 10, color="g", alpha=0.08, label="+-10%")
        ax.set_xlabel("thickness / element size")
        ax.set_ylabel("error (%)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle("Cantilever under its own weight: linear elements lock (too stiff), quadratic ones bend with one layer")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def bench_plot(table: pd.DataFrame, path: Path) -> None:
    """Real-time factor per drone, cost against element count (linear scaling), and speed
    against bending accuracy over the refined flower meshes."""
    fig, axes = plt.subplots(1, 3, figsize=(16, 4))
    base = table[table["series"] == "drone"]
    axes[0].barh(base["drone"], base["realtime_factor"], color="tab:blue")
    axes[0].axvline(10, color="r", ls="--", label="10x real time")
    axes[0].set_xlabel("real-time factor (simulated s / wall s)")
    axes[0].legend()
    scale = table[table["series"] == "scaling"]
    axes[1].loglog(scale["elements"], scale["us_per_substep"], "o-", label="flower, refined")
    if len(scale):
        e0, t0 = scale["elements"].iloc[-1], scale["us_per_substep"].iloc[-1]
        axes[1].loglog(scale["elements"], t0 * scale["elements"] / e0, "k--", lw=0.8, label="linear")
    axes[1].set_xlabel("elements")
    axes[1].set_ylabel("microseconds per substep")
    axes[1].legend()
    axes[1].minorticks_off()
    if "bend_deg" in scale and len(scale):
        axes[2].semilogx(scale["realtime_factor"], scale["bend_deg"], "o-", color="tab:blue")
        for _, r in scale.iterrows():
            axes[2].annotate(f"{r['elements']} tets", (r["realtime_factor"], r["bend_deg"]), fontsize=7,
                             textcoords="offset points", xytext=(4, 4))
        axes[2].axvline(10, color="r", ls="--", label="10x real time")
        axes[2].axhline(scale["bend_deg"].iloc[-1], color="k", ls=":", lw=0.8, label="finest mesh")
        axes[2].set_xlabel("real-time factor")
        axes[2].set_ylabel("petal bend under a fixed load (deg)")
        axes[2].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
