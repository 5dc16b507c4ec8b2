"""Plots every experiment leaves behind, readable at a glance."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from sdexp.figures import pyplot, save_figure

plt = pyplot()


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
    save_figure(fig, path, dpi=120)


def _finish(fig, axes, path: Path) -> None:
    """Grid and legend on every panel, then the figure saved (bench_sim's figures)."""
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def bench_plot(table: pd.DataFrame, path: Path) -> None:
    """Per drone: real-time factor and bend error of both element types; and the flower's
    speed/accuracy frontier (bend error against real-time factor over its refinements)."""
    fig, axes = plt.subplots(1, 4, figsize=(22, 5.5))
    base = table[table["series"] == "drone"]
    colors = {"linear": "tab:orange", "quadratic": "tab:blue"}
    names = list(dict.fromkeys(base["drone"]))
    y = np.arange(len(names))
    elements = list(dict.fromkeys(base["element"]))
    width = 0.8 / max(len(elements), 1)
    for k, element in enumerate(elements):
        rows = base[base["element"] == element].set_index("drone").reindex(names)
        off = (k - (len(elements) - 1) / 2) * width
        axes[0].barh(y + off, rows["realtime_factor"], height=width, color=colors.get(element), label=element)
        axes[1].barh(y + off, 100 * rows["bend_error"], height=width, color=colors.get(element), label=element)
    for ax in axes[:2]:
        ax.set_yticks(y, names)
        ax.invert_yaxis()
    axes[0].axvline(10, color="r", ls="--", label="10x real time")
    axes[0].set_xscale("log")
    axes[0].set_xlabel("real-time factor (simulated s / wall s, 2 cores)")
    axes[0].set_title("speed at the default mesh")
    axes[1].axvspan(-10, 10, color="g", alpha=0.1, label="+-10%")
    axes[1].axvline(0, color="k", lw=0.8)
    axes[1].set_xlabel("bend error against the converged body (%)")
    axes[1].set_title("accuracy at the default mesh (negative: too stiff)")
    scale = table[table["series"] == "scaling"]
    for element, group in scale.groupby("element", sort=False):
        axes[2].semilogx(group["realtime_factor"], 100 * group["bend_error"], "o-", color=colors.get(element),
                         label=f"{group['drone'].iloc[0]}, {element}")
        for _, r in group.iterrows():
            if not np.isfinite(r["realtime_factor"]):
                continue   # blew up: no speed to place it at
            axes[2].annotate(f"{r['elements']}", (r["realtime_factor"], 100 * r["bend_error"]), fontsize=7,
                             textcoords="offset points", xytext=(4, 4))
    axes[2].axvline(10, color="r", ls="--", label="10x real time")
    axes[2].axhspan(-10, 10, color="g", alpha=0.1, label="+-10%")
    axes[2].set_xlabel("real-time factor (labels: elements)")
    axes[2].set_ylabel("bend error (%)")
    axes[2].set_title("speed / accuracy frontier over mesh resolutions")
    res = table[table["series"] == "resolution"]
    for name, group in res.groupby("drone", sort=False):
        cost = group["elements"] * group["substeps_per_step"]
        err = 100 * np.maximum(np.abs(group["compliance_error"]), np.abs(group["bend_error"].fillna(0)))
        axes[3].loglog(cost, err.clip(lower=0.1), "o-", label=name)
    axes[3].axhline(10, color="g", ls="--", label="10%")
    axes[3].set_xlabel("elements x substeps per control step (cost)")
    axes[3].set_ylabel("larger of |bend|, |compliance| error (%)")
    axes[3].set_title("quadratic meshes coarsened x1, x1.4, x2")
    _finish(fig, axes, path)


def variants_plot(table: pd.DataFrame, path: Path) -> None:
    """bench_sim's variant rows, per drone: the real-time factor of each variant (sim.precision x
    sim.mass_scaling), the force kernel's share of the core's peak, and what each costs in
    accuracy (the largest change of the first eight free-free frequencies; the float32 flight's
    RMS bend deviation from float64)."""
    rows = table[table["series"] == "variant"]
    names = list(dict.fromkeys(rows["drone"]))
    kinds = list(dict.fromkeys(rows["variant"]))
    y = np.arange(len(names))
    width = 0.8 / max(len(kinds), 1)
    fig, axes = plt.subplots(1, 3, figsize=(18, 0.45 * len(names) + 2.5), sharey=True)
    for k, kind in enumerate(kinds):
        r = rows[rows["variant"] == kind].set_index("drone").reindex(names)
        off = (k - (len(kinds) - 1) / 2) * width
        axes[0].barh(y + off, r["realtime_factor"], height=width, label=kind)
        axes[1].barh(y + off, 100 * r["peak_share"], height=width, label=kind)
        cost = 100 * np.maximum(r["frequency_change_max"], r["bend_rms_deviation"].fillna(0))
        axes[2].barh(y + off, cost.clip(lower=1e-5), height=width, label=kind)   # the reference: at the floor
    axes[0].set_yticks(y, names)
    axes[0].invert_yaxis()
    axes[0].axvline(1, color="k", lw=0.8)
    axes[0].set_xlabel("real-time factor (simulated s / wall s)")
    axes[0].set_title("speed of each variant")
    axes[1].set_xlabel("force kernel, % of one core's FMA peak (own precision)")
    axes[1].set_title("the kernel against the hardware")
    axes[2].axvline(1, color="r", ls="--", label="1%")
    axes[2].set_xscale("log")
    axes[2].set_xlabel("% off float64 unscaled, the larger of: first 8 frequencies, RMS bend of a flight")
    axes[2].set_title("what it costs in accuracy")
    _finish(fig, axes, path)


def drone_accuracy_plot(table: pd.DataFrame, path: Path) -> None:
    """Bend, compliance and first free-free frequency errors of every drone's default mesh,
    linear beside quadratic (the frequency panel: the first mode's error as a bar, the largest
    of the first eight as a dot)."""
    fig, axes = plt.subplots(1, 3, figsize=(16, 5), sharey=True)
    names = list(dict.fromkeys(table["drone"]))
    y = np.arange(len(names))
    for k, (element, color) in enumerate((("linear", "tab:orange"), ("quadratic", "tab:blue"))):
        rows = table[table["element"] == element].set_index("drone").reindex(names)
        for ax, q in zip(axes, ("bend", "compliance", "freq")):
            ax.barh(y + (k - 0.5) * 0.4, 100 * rows[f"{q}_error"], height=0.4, color=color, label=element)
            ax.errorbar(100 * rows[f"{q}_error"], y + (k - 0.5) * 0.4, xerr=100 * rows[f"{q}_reference_uncertainty"],
                        fmt="none", ecolor="k", lw=0.8)
        if "freq_error_max" in rows:
            axes[2].plot(100 * rows["freq_error_max"], y + (k - 0.5) * 0.4, "o", color=color, mec="k", ms=4)
    for ax, title in zip(axes, ("bend the IMUs read", "compliance (the whole body's stiffness)",
                                "first free-free frequency (dot: worst of 8)")):
        ax.axvspan(-10, 10, color="g", alpha=0.1, label="+-10%")
        ax.axvline(0, color="k", lw=0.8)
        ax.set_xlabel("error against the converged body (%); bars: reference uncertainty")
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.set_xlim(-100, 100)
    axes[0].set_yticks(y, names)
    axes[0].invert_yaxis()
    axes[0].legend(fontsize=8)
    fig.suptitle("Every drone's default mesh against its converged body: linear elements lock, quadratic ones bend")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
