"""``sdexp experiment=validate_fem``: the simulator against physics.

* Cantilever under its own weight, clamped at x = 0: static tip deflection (dynamic
  relaxation) and first bending frequency (free vibration) against Euler-Bernoulli, for a
  refinement series of structured meshes and for a pytetwild mesh at a drone's default
  element size, linear and quadratic elements side by side. Linear tets lock in bending when
  few span the thickness; quadratic ones bend with one layer. The table shows how much, and
  how the errors shrink under refinement.
* Stiff limit: a near-rigid plate under constant thrust follows the analytic rigid-body motion.
* Every drone at its default mesh, both element types, against its converged body (the bend its
  IMUs read and its compliance under a fixed load: sdexp.eval.convergence).
"""
from __future__ import annotations

import logging
from dataclasses import asdict

import numpy as np
import pandas as pd

from sdexp.experiment_params import BeamParams
from sdexp.eval.run import Run
from sdexp.sim.physics.fem import FemModel, build_fem, stable_substep
from sdexp.sim.physics.integrator import Body
from sdexp.sim.physics.quadratic import quadratic_mesh
from sdexp.sim.mesh.structured import box_tets, box_tris

log = logging.getLogger(__name__)


EB_ROOT = 1.8751040687  # first root of cos(x) cosh(x) = -1


class FreeBody(Body):
    """A FEM body with no rotors at its largest stable substep, for validation; ``precision``:
    the elastic forces' arithmetic (sim.precision)."""

    def __init__(self, fem: FemModel, safety: float = 0.8, pinned: np.ndarray | None = None,
                 precision: str = "float64"):
        super().__init__(fem, threads=1, pinned=pinned, precision=precision)
        self.dt = stable_substep(fem, safety)

    def run(self, n: int, damping: float = 0.0, gravity: float = 0.0) -> int:
        """n substeps; returns the largest count of inverted elements seen."""
        return super().run(n, self.dt, None, damping, gravity)[0]


# ------------------------------------------------------------------------------ cantilever

class Beam(BeamParams):
    """The cantilever (its dimensions: experiment.params.beam) and its beam theory."""

    def second_moment(self, dim: int) -> float:
        return (self.width if dim == 3 else 1.0) * self.thickness ** 3 / 12

    def modulus(self, dim: int) -> float:
        """E for a narrow 3D beam, E / (1 - nu^2) in plane strain."""
        return self.youngs_modulus if dim == 3 else self.youngs_modulus / (1 - self.poisson_ratio ** 2)

    def area(self, dim: int) -> float:
        return self.thickness * (self.width if dim == 3 else 1.0)

    def density(self, dim: int) -> float:
        """Chosen so the Euler-Bernoulli tip sag under gravity is ``sag`` x length."""
        EI = self.modulus(dim) * self.second_moment(dim)
        return self.sag * self.length * 8 * EI / (self.area(dim) * 9.81 * self.length ** 4)

    def eb_deflection(self) -> float:
        return self.sag * self.length

    def eb_frequency(self, dim: int) -> float:
        EI = self.modulus(dim) * self.second_moment(dim)
        rA = self.density(dim) * self.area(dim)
        return EB_ROOT ** 2 / (2 * np.pi) * np.sqrt(EI / (rA * self.length ** 4))

    def timoshenko_deflection(self, dim: int) -> float:
        """EB plus the shear deflection w L^2 / (2 kappa G A), kappa = 5/6 (rectangle)."""
        G = self.youngs_modulus / (2 * (1 + self.poisson_ratio))
        w = self.density(dim) * self.area(dim) * 9.81
        return self.eb_deflection() + w * self.length ** 2 / (2 * (5 / 6) * G * self.area(dim))


def structured_beam(beam: Beam, dim: int, layers: int) -> tuple[np.ndarray, np.ndarray]:
    """``layers`` elements through the thickness, near-cubic elements elsewhere."""
    h = beam.thickness / layers
    nx = max(1, round(beam.length / h))
    if dim == 2:
        return box_tris((nx, layers), (beam.length, beam.thickness), (0.0, -beam.thickness / 2))
    nz = max(1, round(beam.width / h))
    return box_tets((nx, layers, nz), (beam.length, beam.thickness, beam.width),
                    (0.0, -beam.thickness / 2, -beam.width / 2))


def cantilever(beam: Beam, points: np.ndarray, elems: np.ndarray, periods: float = 4.0,
               element: str = "linear", precision: str = "float64") -> dict:
    """Static tip sag and first bending frequency of the beam meshed by the linear mesh
    (points, elems), which must span x in [0, length], with ``element`` elements on it, forces
    in ``precision``; nodes at x = 0 are clamped."""
    if element == "quadratic":
        points, elems = quadratic_mesh(points, elems)
    dim = points.shape[1]
    density = beam.density(dim)
    volume = beam.area(dim) * beam.length
    fem = build_fem(points, elems, density * volume, beam.youngs_modulus, beam.poisson_ratio)
    pinned = np.flatnonzero(points[:, 0] < 1e-9)
    body = FreeBody(fem, pinned=pinned, precision=precision)
    tip = np.flatnonzero(points[:, 0] > beam.length - 1e-9)
    f_eb = beam.eb_frequency(dim)
    # dynamic relaxation: mass damping at twice the EB angular frequency decays the first mode
    # critically (every mode at the same rate)
    alpha = 2 * 2 * np.pi * f_eb
    steps = int(np.ceil(12.0 / (alpha / 2) / body.dt))
    inv = body.run(steps, damping=alpha, gravity=9.81)
    sag = -float(np.mean(body.x[tip, 1] - points[tip, 1]))
    # release: undamped free vibration about the rest shape from the sagged shape
    body.v[:] = 0.0
    sample = max(1, int(round(1.0 / (60 * f_eb) / body.dt)))
    n_samples = int(np.ceil(periods * 60))
    ys = np.empty(n_samples)
    for k in range(n_samples):
        inv = max(inv, body.run(sample))
        ys[k] = np.mean(body.x[tip, 1] - points[tip, 1])
    f_sim = _frequency(ys - ys.mean(), sample * body.dt)
    return {
        "elements": len(elems), "dim": dim,
        "sag": sag, "sag_eb": beam.eb_deflection(), "sag_timoshenko": beam.timoshenko_deflection(dim),
        "sag_error": sag / beam.eb_deflection() - 1,
        "freq": f_sim, "freq_eb": f_eb, "freq_error": f_sim / f_eb - 1,
        "substep": body.dt, "inverted": int(inv),
    }


def _frequency(y: np.ndarray, dt: float) -> float:
    """Mean period between upward zero crossings (linear interpolation)."""
    i = np.flatnonzero((y[:-1] < 0) & (y[1:] >= 0))
    if len(i) < 2:
        return float("nan")
    t = (i + (-y[i]) / (y[i + 1] - y[i])) * dt
    return 1.0 / float(np.mean(np.diff(t)))


# ------------------------------------------------------------------------------ rigid limit

def stiff_plate_under_thrust(thrust: float = 6.0, seconds: float = 0.3, youngs_modulus: float = 2e5) -> dict:
    """A stiff 1 m x 0.1 m x 1 m plate of 1 kg with four equal upward forces at its corners
    (applied as nodal forces on the top-face corner patches): rigid theory says it rises with
    a = 4 T / m - g, keeps its orientation and does not deform."""
    pts, tets = box_tets((6, 1, 6), (1.0, 0.1, 1.0), (-0.5, -0.05, -0.5))
    fem = build_fem(pts, tets, 1.0, youngs_modulus, 0.3)
    body = FreeBody(fem)
    top = pts[:, 1] > 0.04
    corners = [np.flatnonzero(top & (np.abs(pts[:, 0] - sx * 0.5) < 1e-9) & (np.abs(pts[:, 2] - sz * 0.5) < 1e-9))
               for sx in (-1, 1) for sz in (-1, 1)]
    for c in corners:
        body.ext[c, 1] += thrust / len(c)
    steps = int(round(seconds / body.dt))
    body.run(steps, gravity=9.81)
    t = steps * body.dt
    com = (fem.mass[:, None] * body.x).sum(0) / fem.mass.sum()
    a = 4 * thrust / fem.mass.sum() - 9.81
    return {"time": t, "rise": float(com[1]), "rise_rigid": 0.5 * a * t * t,
            "drift": float(np.hypot(com[0], com[2])),
            "max_deformation": float(np.abs(body.x - pts - com).max())}


# ------------------------------------------------------------------------------ runner

def run(run: Run) -> dict:
    from sdexp.eval.plots import drone_accuracy_plot, refinement_plot
    from sdexp.sim.drone import drone_names

    cfg, p, out_dir = run.cfg, run.params, run.out_dir
    beam = Beam(**asdict(p.beam))
    rows = []
    for element, layer_lists in p.layers.items():
        for dim in (2, 3):
            for layers in layer_lists[f"{dim}d"]:
                pts, el = structured_beam(beam, dim, layers)
                res = cantilever(beam, pts, el, element=element, precision=cfg.sim.precision)
                rows.append({"element": element, "mesh": f"structured {dim}D", "layers": layers,
                             "edge": beam.thickness / layers, "thickness_over_edge": layers, **res})
                log.info(f"  {element} {dim}D {layers} layers, {len(el)} elements: sag error "
                         f"{res['sag_error']:+.1%}, frequency error {res['freq_error']:+.1%}")
    if p.drone_edge_length:
        from sdexp.sim.mesh.tetmesh import tet_mesh
        edge = float(p.drone_edge_length)
        v, f = _beam_surface(beam)
        pts, el = tet_mesh(v, f, edge)
        for element in p.layers:
            res = cantilever(beam, pts, el, element=element, precision=cfg.sim.precision)
            rows.append({"element": element, "mesh": "pytetwild 3D", "layers": np.nan, "edge": edge,
                         "thickness_over_edge": beam.thickness / edge, **res})
            log.info(f"  {element} pytetwild at edge {edge} m, {len(el)} tets: sag error "
                     f"{res['sag_error']:+.1%}, frequency error {res['freq_error']:+.1%}")
    table = pd.DataFrame(rows)
    run.table(table, "cantilever")
    refinement_plot(table, out_dir / "cantilever.png")
    drone_rows = drone_accuracy(cfg, list(p.drones or drone_names()), p.refine, float(p.bend_load))
    if drone_rows:
        drones = pd.DataFrame(drone_rows)
        run.table(drones, "drones")
        drone_accuracy_plot(drones, out_dir / "drones.png")
    rigid = stiff_plate_under_thrust()
    run.table(pd.DataFrame([rigid]), "stiff_limit")
    metrics = {"rigid_rise_error": rigid["rise"] / rigid["rise_rigid"] - 1}
    for r in drone_rows:
        metrics[f"{r['drone']}_{r['element']}_bend_error"] = r["bend_error"]
        metrics[f"{r['drone']}_{r['element']}_compliance_error"] = r["compliance_error"]
        metrics[f"{r['drone']}_{r['element']}_freq_error"] = r["freq_error"]
        metrics[f"{r['drone']}_{r['element']}_freq_error_max"] = r["freq_error_max"]
    for r in rows:
        key = r["element"] + "_" + (f"pytetwild_edge{r['edge']:g}" if np.isnan(r["layers"])
                                    else f"{r['mesh'].replace(' ', '_')}_{int(r['layers'])}layers")
        metrics[f"sag_error_{key}"] = r["sag_error"]
        metrics[f"freq_error_{key}"] = r["freq_error"]
    return metrics


def drone_accuracy(cfg, names: list[str], refine: dict[str, list[float]], load: float) -> list[dict]:
    """Every named drone at its default mesh, linear and quadratic, against the converged body
    (sdexp.eval.convergence): the bend its IMUs read and its compliance under a fixed load, and
    its first free-free frequencies."""
    from sdexp.eval.bench_sim import drone_config
    from sdexp.eval.convergence import converged_response, response_errors
    from sdexp.sim.drone import build_drone

    rows, gravity = [], float(cfg.sim.gravity)
    for name in names:
        d = drone_config(cfg, name)
        ref = converged_response(d, cfg.cache_dir, refine[f"{d.dim}d"], gravity, load)
        for element in ("linear", "quadratic"):
            drone = build_drone(d, cfg.cache_dir, element)
            rows.append({"drone": name, "element": element, "elements": drone.fem.n_elems,
                         **response_errors(drone, ref, gravity, load)})
            r = rows[-1]
            log.info(f"  {name} {element}: bend error {r['bend_error']:+.1%}, compliance error "
                     f"{r['compliance_error']:+.1%}, first frequency {r['freq_error']:+.1%} "
                     f"(worst of {len(ref['freq_converged'])}: {r['freq_error_max']:+.1%})")
    return rows


def _beam_surface(beam: Beam) -> tuple[np.ndarray, np.ndarray]:
    """Closed outward triangle surface of the 3D beam box."""
    L, t, w = beam.length, beam.thickness, beam.width
    v = np.array([[x, y, z] for x in (0, L) for y in (-t / 2, t / 2) for z in (-w / 2, w / 2)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    f = np.array(f)
    # orient outward: the signed volume must be positive
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    if np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() < 0:
        f = f[:, ::-1]
    return v, f
