"""``sdexp experiment=gallery``: every drone's mesh with its rotors and IMUs, at a glance."""
from __future__ import annotations

import numpy as np
import pandas as pd

from sdexp.eval.bench_sim import drone_config
from sdexp.eval.run import Run
from sdexp.sim.drone import build_drone, drone_names
from sdexp.sim.mesh.surface import face_normals


def drawn(params) -> list[str]:
    """The drones the gallery draws: ``experiment.params.drones``, null (or []) the paper's twelve.
    A drone of one's own is drawn when listed (``experiment.params.drones=[custom]``); the run's
    preflight refuses it named by ``drone=`` alone (sdexp.eval.run.check_overrides_reach)."""
    return list(params.drones or drone_names())


def run(run: Run) -> dict:
    from sdexp.figures import pyplot
    plt = pyplot()
    from sdexp.log import Phase

    cfg = run.cfg
    names = drawn(run.params)
    cols = 4
    rows = int(np.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.6 * rows), squeeze=False)
    table = []
    for ax, name in zip(axes.ravel(), Phase("gallery", len(names), "drones").iterate(names)):
        d = drone_config(cfg, name)
        drone = build_drone(d, cfg.cache_dir, cfg.sim.element)
        x = drone.fem.rest
        plane = [0, 2] if drone.dim == 3 else [0, 1]
        if drone.dim == 3:  # top view of the upper surface
            up = drone.boundary[face_normals(x, drone.boundary)[:, 1] > 0]
            ax.triplot(x[:, 0], x[:, 2], up, color="0.75", lw=0.4)
        else:
            ax.triplot(x[:, 0], x[:, 1], drone.fem.elems[:, :3], color="0.75", lw=0.4)   # corners
        r = drone.rotors.anchors[:, plane]
        ax.scatter(*r.T, s=60, c="tab:red", marker="o", label="rotor", zorder=3)
        for k in range(drone.num_rotors):
            verts = drone.rotors.verts[drone.rotors.vert_ptr[k]:drone.rotors.vert_ptr[k + 1]]
            ax.scatter(*x[verts][:, plane].T, s=4, c="tab:red", zorder=2)
        imu_pos = np.einsum("kp,kpd->kd", drone.imus.w, x[drone.imus.idx])[:, plane]
        lay = drone.layout
        ax.scatter(*imu_pos[lay.periph_idx].T, s=40, c="tab:blue", marker="s", label="IMU (s)", zorder=4)
        for i, k in enumerate(lay.periph_idx):
            ax.annotate(str(i), imu_pos[k], fontsize=7, color="tab:blue", xytext=(3, 3), textcoords="offset points")
        ax.scatter(*imu_pos[lay.frame_idx].T, s=70, facecolors="none", edgecolors="k", marker="D",
                   label="frame IMU (e)", zorder=5)
        ax.set_title(f"{name} ({drone.dim}D, {drone.fem.n_elems} elements)", fontsize=10)
        ext = np.ptp(x[:, plane], axis=0)
        ax.set_aspect("equal" if ext.max() < 8 * ext.min() else "auto")  # the rod is 80:1
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("z (m)" if drone.dim == 3 else "y (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        table.append({"drone": name, "dim": drone.dim, "elements": drone.fem.n_elems,
                      "vertices": len(x), "rotors": drone.num_rotors, "sensors": lay.n_s})
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("sdexp drones: 3D top views (X-Z, +Y up), 2D in X-Y; s-order numbered", fontsize=12)
    fig.tight_layout()
    run.figure(fig, "drones", dpi=110)
    run.table(pd.DataFrame(table), "drones")
    return {f"{r['drone']}_elements": r["elements"] for r in table}

