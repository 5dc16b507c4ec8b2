"""``sdexp experiment=hover_deform``: active deformation while hovering (the paper's "Aerial
Deformation"). The flower holds its position and level attitude while its odd petals (1, 3, 5,
7: "lateral") rise by ``angle_deg`` and the even ones (2, 4, 6, 8: "axial") stay flat, then the
roles switch. The paper's claim: after the initial drop, rotation within +-3 deg and position
within +-5 cm.

Writes ``hover_deform.csv`` (the flight), ``hover_deform.png`` (bend angles against their goal;
attitude and position deviation with the +-3 deg / +-5 cm band) and metrics measured after
``settle_seconds``: max attitude deviation (deg), max position deviation (cm), RMS bend
tracking error (deg), and whether the paper's band held. With ``experiment.params.animate``:
``hover_deform.mp4`` (the deforming drone) and ``hover_deform_vtu/hover_deform.pvd`` (ParaView).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sdexp.eval.flights import Setup, ending, flight_table
from sdexp.eval.run import Run


def schedule(n_s: int, angle: float, settle: float, ramp: float, hold: float) -> tuple[list, list]:
    """Keyframes: flat, odd petals up, swap, even petals up, flat again."""
    odd = np.array([angle if i % 2 == 0 else 0.0 for i in range(n_s)])   # petals 1, 3, 5, ...
    even = np.array([0.0 if i % 2 == 0 else angle for i in range(n_s)])
    flat = np.zeros(n_s)
    t, times, targets = settle, [0.0, settle], [flat, flat]
    for shape in (odd, even, flat):
        t += ramp
        times.append(t)
        targets.append(shape)
        t += hold
        times.append(t)
        targets.append(shape)
    return times, [list(x) for x in targets]


def run(run: Run) -> dict:
    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    setup = Setup(cfg)
    dyn = setup.dyn
    times, targets = schedule(dyn.n_s, np.deg2rad(float(p.angle_deg)), float(p.settle_seconds),
                              float(p.ramp_seconds), float(p.hold_seconds))
    start = np.zeros(dyn.dim)
    task = setup.task(start, start, times[-1], bend_times=times, bend_targets=targets)
    sim = setup.simulator()
    rec = setup.recorder(bool(p.animate))
    flight, m = setup.fly(sim, setup.controller("ours", sim), task, "hover and deform", recorder=rec)
    setup.animate(out_dir, "hover_deform", rec, f"{cfg.drone.name}: hover with active deformation "
                  f"({float(p.angle_deg):g} deg); {ending(m)}")
    tab = flight_table(flight, dyn)
    run.table(tab, "hover_deform")
    a = flight.arrays()
    sl = dyn.slices
    after = a["t"] >= float(p.settle_seconds)
    att = np.rad2deg(np.abs(a["x"][after][:, sl["e"]])) if after.any() else np.full((1, dyn.n_e), np.nan)
    pos = 100 * np.abs(a["x"][after][:, sl["p"]] - a["goal"][after][:, sl["p"]]) if after.any() else np.full((1, dyn.dim), np.nan)
    bend_err = np.rad2deg(a["x"][after][:, sl["s"]] - a["goal"][after][:, sl["s"]]) if after.any() else np.full((1, dyn.n_s), np.nan)
    out = {**{f"flight_{k}": v for k, v in m.items()},
           "max_attitude_deviation_deg": float(att.max()), "max_position_deviation_cm": float(pos.max()),
           "bend_rms_error_deg": float(np.sqrt(np.mean(bend_err ** 2))),
           "paper_band_held": bool(m["survived"] and att.max() <= 3.0 and pos.max() <= 5.0)}
    _plot(tab, a, dyn, float(p.settle_seconds), out_dir / "hover_deform.png", cfg.drone.name, out)
    return out


def _plot(tab, a, dyn, settle: float, path: Path, drone: str, out: dict) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()

    sl = dyn.slices
    t = a["t"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    colors = plt.cm.tab10(np.arange(dyn.n_s) % 10)
    for i in range(dyn.n_s):
        axes[0].plot(t, np.rad2deg(a["x"][:, sl["s"]][:, i]), color=colors[i], lw=1, label=f"petal {i + 1}")
        axes[0].plot(t, np.rad2deg(a["goal"][:, sl["s"]][:, i]), color=colors[i], ls="--", lw=0.8)
    axes[0].set_ylabel("bend angle s (deg); dashed: goal")
    axes[0].legend(fontsize=6, ncol=2)
    for j, nm in enumerate(["e_x", "e_y", "e_z"][: dyn.n_e]):
        axes[1].plot(t, np.rad2deg(a["x"][:, sl["e"]][:, j]), label=nm)
    axes[1].axhspan(-3, 3, color="g", alpha=0.1, label="+-3 deg (paper)")
    axes[1].set_ylabel("attitude (deg)")
    axes[1].legend(fontsize=7)
    for j, nm in enumerate(["x", "y", "z"][: dyn.dim]):
        axes[2].plot(t, 100 * (a["x"][:, sl["p"]][:, j] - a["goal"][:, sl["p"]][:, j]), label=nm)
    axes[2].axhspan(-5, 5, color="g", alpha=0.1, label="+-5 cm (paper)")
    axes[2].set_ylabel("position deviation (cm)")
    axes[2].legend(fontsize=7)
    for ax in axes:
        ax.axvline(settle, color="k", lw=0.6, ls=":")
        ax.set_xlabel("t (s)")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{drone}: hover with active deformation -- after {settle:g} s: attitude within "
                 f"{out['max_attitude_deviation_deg']:.1f} deg, position within {out['max_position_deviation_cm']:.1f} cm")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def summary(params, metrics: dict) -> str:
    """The measured deviations beside the paper's band."""
    m = metrics
    return "\n".join([
        f"  survived {m['flight_survival_time']:.1f} s{'' if m['flight_survived'] else ' (' + m['flight_failure'] + ')'}",
        f"  max attitude deviation {m['max_attitude_deviation_deg']:.2f} deg    (paper: within 3 deg)",
        f"  max position deviation {m['max_position_deviation_cm']:.1f} cm     (paper: within 5 cm)",
        f"  rms bend error {m['bend_rms_error_deg']:.2f} deg; the paper's band {'held' if m['paper_band_held'] else 'not held'}"])
