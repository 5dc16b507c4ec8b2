"""``sdexp experiment=obstacle``: the paper's obstacle avoidance. The star flies with a constant
velocity in (+X, +Y) towards a gap between box obstacles (``sim.obstacles``) narrower than its
Z width, folding the two wings that lie along Z (raising their bend angles to ``fold_deg``) while
holding its Z position.

Writes ``obstacle.csv`` (the flight), ``obstacle.png`` (wing pitch, Z width, Z deviation and the
path through the gap seen from above) and metrics: wing pitch change (deg), the fold the body
can hold at all (``fold_limit_deg``, see ``fold_limit``), width reduction (%),
max Z deviation (m), whether the drone touched an obstacle, and ``passed``: beyond the blocks at
the end, no contact, and inside the opening while level with them (round, over or under the
blocks is not passing).
The width is the mesh's Z extent: a tumbling drone narrows it too, so read it with the pitch.
With ``experiment.params.animate``: ``obstacle.mp4`` (the drone and the blocks) and
``obstacle_vtu/obstacle.pvd`` (the mesh series for ParaView).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sdexp.eval.flights import Setup, ending, flight_table
from sdexp.eval.run import Run
from sdexp.sim.rigid.statics import held_bend, outer_rotors


def folding_wings(r_hat: np.ndarray) -> np.ndarray:
    """Indices of the peripheral sensors on the wings that lie along Z (they set the Z width)."""
    return np.flatnonzero(np.abs(r_hat[:, 2]) > np.abs(r_hat[:, 0]))


def fold_limit(drone, sim_cfg, wings: np.ndarray, seconds: float = 3.0) -> float:
    """The bend (deg) the folding wings hold under the strongest deformation pattern (no net lift
    or tilting torque) that favours their rotors (``statics.held_bend``): an upper bound on the
    fold any controller can ask of this body (the least of the folding wings' bends)."""
    bends = held_bend(drone, sim_cfg, outer_rotors(drone, along_z=True), None, seconds)
    return float(bends[wings].min())


def touching(points: np.ndarray, boxes, margin: float = 1e-3) -> bool:
    for b in boxes:
        lo, hi = np.asarray(b.min) - margin, np.asarray(b.max) + margin
        if np.any(np.all((points >= lo) & (points <= hi), axis=1)):
            return True
    return False


def run(run: Run) -> dict:
    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    setup = Setup(cfg)
    dyn = setup.dyn
    if dyn.dim != 3:
        raise ValueError("the obstacle scene is 3D (a gap in Z): pick a 3D drone")
    wings = folding_wings(setup.drone.layout.r_hat)
    fold = np.zeros(dyn.n_s)
    fold[wings] = np.deg2rad(float(p.fold_deg))
    t0, t1 = float(p.fold_start), float(p.fold_start) + float(p.fold_seconds)
    start = np.zeros(3)
    task = setup.task(start, start, float(p.seconds), velocity=np.asarray(p.velocity, float),
                      bend_times=[0.0, t0, t1], bend_targets=[np.zeros(dyn.n_s), np.zeros(dyn.n_s), fold])
    sim = setup.simulator()
    boxes = list(cfg.sim.obstacles)
    rest_width = float(np.ptp(setup.drone.fem.rest[:, 2]))
    widths, contact = [], []

    def watch(s):
        widths.append(float(np.ptp(s.x[:, 2])))
        contact.append(touching(s.x, boxes))

    rec = setup.recorder(bool(p.animate))
    flight, m = setup.fly(sim, setup.controller("ours", sim), task, "obstacle", watch, recorder=rec)
    setup.animate(out_dir, "obstacle", rec, f"{cfg.drone.name}: through the gap, folding to "
                  f"{float(p.fold_deg):g} deg; {ending(m)}")
    tab = flight_table(flight, dyn)
    tab["width_z"] = [rest_width] + widths[: len(tab) - 1]
    tab["contact"] = [False] + contact[: len(tab) - 1]
    run.table(tab, "obstacle")
    a = flight.arrays()
    gap_start = min((float(b.min[0]) for b in boxes), default=0.0)
    gap_end = max((float(b.max[0]) for b in boxes), default=0.0)
    half_gap = 0.5 * (_gap_width(boxes) or 0.0)
    hit = bool(np.any(tab["contact"]))
    # through the gap: while the centre is level with the blocks it stays inside the opening
    # (between the side blocks in Z, above the bottom one and below the sides' tops in Y);
    # going round, over or under the blocks is not passing
    level = (tab["x"] >= gap_start) & (tab["x"] <= gap_end)
    y_low, y_high = _gap_heights(boxes)
    inside = (np.abs(tab["z"]) < half_gap) & (tab["y"] > y_low) & (tab["y"] < y_high)
    through = bool(level.any() and inside[level].all())
    pitch = np.rad2deg(a["x"][:, dyn.slices["s"]][:, wings]) if len(wings) else np.zeros((len(a["t"]), 1))
    out = {**{f"flight_{k}": v for k, v in m.items()},
           "wing_pitch_change_deg": float(pitch.min(axis=1).max() - pitch[0].min()) if len(pitch) else 0.0,
           "fold_limit_deg": fold_limit(setup.drone, cfg.sim, wings) if len(wings) else 0.0,
           "width_reduction_percent": 100.0 * (1.0 - min(tab["width_z"]) / rest_width),
           "max_z_deviation_m": float(np.abs(a["x"][:, dyn.slices["p"]][:, 2]).max()),
           "hit_obstacle": hit,
           "passed": bool(not hit and through and a["x"][-1, dyn.slices["p"]][0] > gap_end and m["survived"])}
    _plot(tab, pitch, float(p.fold_deg), boxes, rest_width, out_dir / "obstacle.png", cfg.drone.name, out)
    return out


def _plot(tab, pitch, fold_deg: float, boxes, rest_width: float, path: Path, drone: str, out: dict) -> None:
    from sdexp.figures import pyplot, save_figure
    plt = pyplot()
    from matplotlib.patches import Rectangle

    t = tab["t"]
    fig, axes = plt.subplots(1, 4, figsize=(18, 4))
    axes[0].plot(t, pitch)
    axes[0].axhline(fold_deg, color="k", ls=":", lw=0.8, label="asked")
    axes[0].axhline(out["fold_limit_deg"], color="tab:red", ls="--", lw=0.8,
                    label="held by the strongest\nthrust pattern (open loop)")
    axes[0].legend(fontsize=8)
    axes[0].set_ylabel("pitch of the folding wings (deg)")
    axes[1].plot(t, tab["width_z"], color="k")
    axes[1].axhline(rest_width, color="k", ls=":", lw=0.8)
    gaps = _gap_width(boxes)
    if gaps is not None:
        axes[1].axhline(gaps, color="tab:red", ls="--", lw=0.8, label="gap width")
        axes[1].legend(fontsize=8)
    axes[1].set_ylabel("Z width (m)")
    axes[2].plot(t, tab["z"], color="tab:blue")
    axes[2].axhspan(-0.05, 0.05, color="g", alpha=0.1, label="+-5 cm (paper)")
    axes[2].set_ylabel("Z deviation (m)")
    axes[2].legend(fontsize=8)
    for ax in axes[:3]:
        ax.set_xlabel("t (s)")
        ax.grid(alpha=0.3)
    ax = axes[3]
    for b in boxes:
        ax.add_patch(Rectangle((b.min[0], b.min[2]), b.max[0] - b.min[0], b.max[2] - b.min[2], color="0.6"))
    ax.plot(tab["x"], tab["z"], color="tab:blue")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_aspect("equal")
    ax.set_title("path from above", fontsize=9)
    ax.grid(alpha=0.3)
    fig.suptitle(f"{drone}: obstacle -- pitch +{out['wing_pitch_change_deg']:.0f} deg, width -"
                 f"{out['width_reduction_percent']:.0f}%, Z deviation {out['max_z_deviation_m']:.2f} m, "
                 f"{'passed' if out['passed'] else ('hit' if out['hit_obstacle'] else 'did not pass')}")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def _gap_heights(boxes) -> tuple[float, float]:
    """Y range of the opening: above the blocks that span z = 0, below the tops of the others."""
    under = [b.max[1] for b in boxes if b.min[2] < 0 < b.max[2]]
    sides = [b.max[1] for b in boxes if not b.min[2] < 0 < b.max[2]]
    return (max(under) if under else -np.inf), (min(sides) if sides else np.inf)


def _gap_width(boxes) -> float | None:
    """Clear Z width between the boxes that bound the path (those on either side of z = 0)."""
    above = [b.min[2] for b in boxes if b.min[2] > 0]
    below = [b.max[2] for b in boxes if b.max[2] < 0]
    return (min(above) - max(below)) if above and below else None


def summary(params, metrics: dict) -> str:
    """Fold, narrowing and Z hold beside the paper's figures."""
    m = metrics
    result = "passed" if m["passed"] else ("hit the blocks" if m["hit_obstacle"] else "did not pass")
    return "\n".join([
        f"  wing fold {m['wing_pitch_change_deg']:.1f} deg   (paper: > 73 deg; open-loop limit {m['fold_limit_deg']:.0f} deg)",
        f"  narrower by {m['width_reduction_percent']:.1f}%  (paper: > 30%)",
        f"  max Z deviation {m['max_z_deviation_m']:.2f} m  (paper: < 0.05 m)",
        f"  {result}; flight {m['flight_survival_time']:.2f} s{', ' + m['flight_failure'] if m['flight_failure'] else ''}"])
