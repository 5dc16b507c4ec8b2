"""How far a drone's mesh is from the continuum it models: the bend under one fixed load on the
default mesh and on three refinements of it, with the converged bend from Richardson
extrapolation (linear tets at the drones' default resolution bend about half as much as the
material they model; quadratic ones should not).

The load: every node's weight, the design's hover thrust (geometry.hover_thrust at the design's
rotor anchors and normals) and ``load`` N more on each outer rotor (statics.outer_rotors), along
the design's rotor normals, spread over each patch as the simulator spreads it; the net force and torque this leaves are balanced by the
rigid acceleration they cause, as in free flight (inertia relief, d'Alembert). The same for
every drone (a two-rotor drone has no pattern free of net lift to push with).

The solve: the static linear response K u = f of the free body (three nodes hold the six rigid
motions; the balanced load makes the answer independent of which), K the stiffness of the
simulator's co-rotated elements at rest (assembled here; a test checks it against the kernels'
forces). Why static and linear: a dynamic hold measures the floppy drones' transients (the
rod's first free mode has a 9 s period and relaxes over tens of seconds), and the locking
this measures is a stiffness error, the same in the linear regime as near it.

The measures: the RMS over the peripheral IMUs of the bend angle s (deg), read by the sensor
pipeline from the rest positions plus the displacement (scaled to a small strain and back: s is
linear in u there); the compliance fb . u, the whole body's stiffness (static_response); and
the first eight free-free frequencies, which no load enters.

The references keep the design's outline exactly on every mesh, refined in the plane and
through the thickness alike (``refined``): Richardson across meshes of different bodies
extrapolates to none of them.

Richardson: element sizes h (mean element volume's cube root, area's square root in 2D:
unstructured meshes do not refine by the nominal edge ratio), bends b on three meshes, fit
b = b_inf + C h^p exactly (p by bisection). Where they do not converge monotonically, b_inf is
the finest bend and its spread to the next the uncertainty.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from dataclasses import replace

from sdexp.cache import cached_arrays, config_key, key_of
from sdexp.errors import UserError
from sdexp.sim.drone import build_drone, make_shape
from sdexp.sim.physics.fem import FemModel
from sdexp.sim.physics.modes import free_frequencies, rigid_modes, stiffness
from sdexp.sim.rigid.geometry import hover_thrust, rigid_body
from sdexp.sensing import decompose
from sdexp.sim.sensors import read_imus
from sdexp.sim.rigid.statics import outer_rotors

FORMAT = 9   # 6: the load from the design's rotor anchors and normals (fixed_load); 7: the drone's key fields;
             # 8-9: exact outlines, layers with r, the disc load, the balanced load's work, free-free frequencies
MODES = 8    # free-free frequencies compared
DIRECT_MAX_DOFS = 500_000  # SuperLU's fill grows fast: the leaf's finest reference, 251k unknowns, takes
                           # 6 min and 3 GB (smoothed-aggregation AMG, tried, stalls on that thin plate)


def balanced(fem: FemModel, f: np.ndarray) -> np.ndarray:
    """Nodal forces f (nv, dim) less the net force and torque they carry, balanced by the rigid
    acceleration they cause (mass-weighted: d'Alembert's inertia relief of a free body)."""
    d = fem.dim
    Rm = rigid_modes(fem.rest)
    MR = np.repeat(fem.mass, d)[:, None] * Rm
    return (f.ravel() - MR @ np.linalg.solve(Rm.T @ MR, Rm.T @ f.ravel())).reshape(-1, d)


def static_displacement(fem: FemModel, f: np.ndarray) -> np.ndarray:
    """u (nv, dim) of the free body under nodal forces f (nv, dim), with what net force and
    torque f has balanced by the rigid acceleration it causes (``balanced``)."""
    d = fem.dim
    Rm = rigid_modes(fem.rest)
    fb = balanced(fem, f).ravel()
    # hold the rigid motions: node a fully, b in the directions not along a-b, c in the normal
    x = fem.rest
    a = int(np.argmin(x[:, 0]))
    b = int(np.argmax(np.linalg.norm(x - x[a], axis=1)))
    fixed = [a * d + k for k in range(d)]
    axis = int(np.argmax(np.abs(x[b] - x[a])))
    fixed += [b * d + k for k in range(d) if k != axis]
    if d == 3:
        ab = (x[b] - x[a]) / np.linalg.norm(x[b] - x[a])
        off = np.linalg.norm(np.cross(x - x[a], ab), axis=1)
        c = int(np.argmax(off))
        n = np.cross(ab, x[c] - x[a])
        fixed.append(c * d + int(np.argmax(np.abs(n))))
    free = np.setdiff1d(np.arange(len(fb)), fixed)
    K = stiffness(fem)[free][:, free].tocsr()
    u = np.zeros(len(fb))
    if len(free) > DIRECT_MAX_DOFS:
        raise UserError(f"a reference mesh of {len(free)} unknowns is beyond the direct solve's "
                        f"{DIRECT_MAX_DOFS}: choose smaller experiment.params.refine factors")
    u[free] = spla.spsolve(K.tocsc(), fb[free])
    u = u - Rm @ np.linalg.lstsq(Rm, u, rcond=None)[0]   # the rigid part is arbitrary: drop it
    return u.reshape(-1, d)


def load_thrusts(drone, gravity: float, load: float) -> np.ndarray:
    """The rotor thrusts of the module's load (N), along ``drone.rotors.normals``."""
    fem, rot = drone.fem, drone.rotors
    mass, com, _, _, _ = rigid_body(fem.rest, fem.mass, rot, np.eye(fem.dim))
    return hover_thrust(mass, rot.anchors - com, rot.normals, gravity) + load * outer_rotors(drone)


def fixed_load(drone, gravity: float, load: float) -> np.ndarray:
    """Nodal forces (nv, dim) of the module's load. The thrusts come from the design (its rotor
    anchors and normals, not the mesh's patch normals) so that every mesh of a drone carries the
    same load: hover_thrust's choice between thrust patterns turns on how far the rotors tilt,
    and a patch normal a degree off on one mesh flipped the octopus's head rotor between 0 and
    1.1 N (its compliance jumped 20% between neighbouring refinements). Spread over each patch
    as the simulator spreads it: a uniform traction over the patch's disc (sim.mesh.traction),
    a load that converges with the mesh."""
    fem, rot = drone.fem, drone.rotors
    u = load_thrusts(drone, gravity, load)
    f = np.zeros_like(fem.rest)
    f[:, 1] -= fem.mass * gravity
    for r in range(rot.count):
        k = slice(rot.vert_ptr[r], rot.vert_ptr[r + 1])
        np.add.at(f, rot.verts[k], u[r] * rot.weights[k][:, None] * rot.normals[r])
    return f


def static_response(drone, gravity: float = 9.81, load: float = 2.0, modes: int = MODES) -> dict:
    """Under the fixed load, static and linear: ``bend``, the RMS bend (deg) of the peripheral
    IMUs as the sensor pipeline reads it, and ``compliance``, the work of the balanced load
    fb . u (J): the stiffness of the whole body (for one load a conforming mesh underestimates
    it, too stiff). The balanced load's work does not depend on the rigid part of u, which is
    arbitrary (the unbalanced load dotted with u did: -9% to +20% of it). The bend is what the controller sees,
    but it is read from the few surface nodes inside each IMU patch; where it is below a degree
    (the compact 2D drones) which nodes fall inside moves it by more than the elements do.
    And ``freq``, the first ``modes`` free-free frequencies (Hz, HRZ-lumped mass as simulated;
    none for 0): a yardstick that no load or patch placement enters."""
    fem = drone.fem
    fb = balanced(fem, fixed_load(drone, gravity, load))
    out = bend_and_compliance(drone, fb, static_displacement(fem, fb))
    if modes:
        out["freq"] = free_frequencies(fem, k=modes)
    return out


def bend_and_compliance(drone, fb: np.ndarray, u: np.ndarray) -> dict:
    """``static_response``'s measures of a displacement u (nv, dim) under the balanced load fb:
    the RMS bend (deg) its IMUs read and the load's work (J)."""
    fem = drone.fem
    out = {"compliance": float(np.sum(fb * u)), "bend": float("nan")}
    if drone.layout.n_s:
        eps = 1e-4 * np.ptp(fem.rest, axis=0).max() / max(np.abs(u).max(), 1e-300)
        x = fem.rest + eps * u
        s = decompose(read_imus(0.0, x, np.zeros_like(x), drone.imus), drone.layout).s / eps
        out["bend"] = float(np.rad2deg(np.sqrt(np.mean(np.square(s)))))
    return out


def element_size(drone) -> float:
    fem = drone.fem
    return float((fem.vol.sum() / fem.n_elems) ** (1.0 / fem.dim))


def richardson(h, b) -> tuple[float, float, float]:
    """(b_inf, order p, uncertainty) from three (h, b), coarse to fine."""
    h, b = np.asarray(h, float), np.asarray(b, float)
    d1, d2 = b[0] - b[1], b[1] - b[2]
    if not (d1 * d2 > 0 and abs(d2) < abs(d1) and h[0] > h[1] > h[2]):
        return float(b[2]), float("nan"), float(abs(d2))

    def gap(p):  # (h1^p - h2^p) / (h2^p - h3^p) against the observed ratio
        return (h[0] ** p - h[1] ** p) / (h[1] ** p - h[2] ** p) - d1 / d2
    lo, hi = 0.1, 8.0
    if gap(lo) * gap(hi) > 0:
        return float(b[2]), float("nan"), float(abs(d2))
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(lo) * gap(mid) > 0 else (lo, mid)
    p = 0.5 * (lo + hi)
    C = d2 / (h[1] ** p - h[2] ** p)
    b_inf = b[2] - C * h[2] ** p
    return float(b_inf), float(p), float(abs(b_inf - b[2]))


REFERENCE_ENVELOPE = 2e-4   # a file drone's references: fTetWild's surface envelope (its own: 1e-3)


def refined(mesh, r: float, dim: int):
    """The reference mesh settings (a MeshConfig) r times finer: edge_length / r, and in 3D always a plate
    extruded through the thickness (layers x r, at least 4/3 r when the drone has fewer than two,
    rounded up: refined through the thickness as in the plane) with the design's outline kept
    exactly (``outline: exact``, graded toward its re-entrant corners): fTetWild's meshes keep
    the surface only to its envelope (a few mm, which on a 0.15 m shell is 20% of its bending
    stiffness) however fine they are, and an evenly resampled outline cuts the notches between
    petals (the flower's at 0.63-0.69 m from the centre instead of 0.60), so each refinement
    would be another body.

    A drone of one's own (``mesh.file``) has no design outline: its file is the body, and the
    references are fTetWild meshes of that surface r times finer whose envelope is
    ``REFERENCE_ENVELOPE`` (a fifth of fTetWild's own), so that they converge to the file's body
    and not to a surface a few millimetres off it."""
    out = {"edge_length": float(mesh.edge_length) / r}
    if mesh.file is not None:
        return replace(mesh, **out, envelope=REFERENCE_ENVELOPE)
    if dim == 3:
        out["layers"] = int(np.ceil(max(4 / 3, mesh.layers) * r - 1e-9))
        out["outline"] = "exact"
    return replace(mesh, **out)


def converged_response(drone_cfg, cache_dir: str, refine: list[float], gravity: float = 9.81,
                       load: float = 2.0, element: str = "quadratic") -> dict:
    """static_response of ``element`` meshes r times finer (``refined``) for r in ``refine`` and
    the Richardson extrapolate of each quantity (``<q>_converged``, ``<q>_order``,
    ``<q>_uncertainty``; per mode for the frequencies, lists); cached (fine 3D meshes take
    minutes to make)."""
    if drone_cfg.mesh.file is not None:
        if make_shape(drone_cfg).volume_mesh is not None:
            raise UserError(f"drone {drone_cfg.name}: {drone_cfg.mesh.file} is a volume mesh, used as given, so "
                            "there is no finer mesh of it to converge to; give its surface (STL, OBJ, PLY, ...) "
                            "to validate it against its converged body")
    payload = {"drone": config_key(drone_cfg), "refine": list(refine),
               "gravity": gravity, "load": load, "element": element, "modes": MODES}

    def make():
        from sdexp.log import Phase
        rows, freqs = [], []
        for r in Phase(f"converged reference of {drone_cfg.name} ({element}, {len(refine)} meshes)",
                       len(refine), "refinements").iterate(refine):
            cfg = replace(drone_cfg, mesh=refined(drone_cfg.mesh, r, int(drone_cfg.dim)))
            drone = build_drone(cfg, cache_dir, element)
            res = static_response(drone, gravity, load)
            rows.append([element_size(drone), drone.fem.n_elems, res["bend"], res["compliance"]])
            freqs.append(res["freq"])
        h, n, bend, compliance = np.array(rows).T
        return {"h": h, "elements": n, "bend": bend, "compliance": compliance, "freq": np.array(freqs)}

    a = cached_arrays(cache_dir, key_of("response", FORMAT, payload), make)
    out = {k: a[k].tolist() for k in a}
    for q in ("bend", "compliance"):
        value, order, unc = richardson(a["h"], a[q])
        out.update({f"{q}_converged": value, f"{q}_order": order, f"{q}_uncertainty": unc})
    fits = [richardson(a["h"], a["freq"][:, k]) for k in range(a["freq"].shape[1])]
    out.update({f"freq_{w}": [f[i] for f in fits] for i, w in enumerate(("converged", "order", "uncertainty"))})
    return out


def response_errors(drone, reference: dict, gravity: float = 9.81, load: float = 2.0) -> dict:
    """The drone's static response and free-free frequencies beside the converged ones
    (``converged_response``), as relative errors (negative: stiffer for the bend and the
    compliance, lower for a frequency; a too stiff mesh bends less and rings higher), with the
    reference's own uncertainty (``<q>_error``). The frequencies as ``freq_error`` (the first mode's),
    ``freq_error_max`` (the largest in size of the first MODES, signed) and ``freq_errors``."""
    res = static_response(drone, gravity, load)
    out = {}
    for q in ("bend", "compliance"):
        ref = reference[f"{q}_converged"]
        out.update({q: res[q], f"{q}_converged": ref, f"{q}_error": res[q] / ref - 1,
                    f"{q}_reference_uncertainty": reference[f"{q}_uncertainty"] / abs(ref)})
    ref = np.asarray(reference["freq_converged"])
    err = res["freq"] / ref - 1
    out.update({"freq": float(res["freq"][0]), "freq_converged": float(ref[0]), "freq_error": float(err[0]),
                "freq_error_max": float(err[np.argmax(np.abs(err))]),
                "freq_reference_uncertainty": float(np.max(np.asarray(reference["freq_uncertainty"]) / ref)),
                "freq_errors": " ".join(f"{e:+.4f}" for e in err)})
    return out


def reduced_static_errors(drone, model, gravity: float, load: float) -> dict:
    """validate_fem's load, linear statics: the full model's solve and the reduced one's
    (Phi K_r^-1 Phi^T fb, K_r the step's rest stiffness: the cubature's, its linear modes' block
    exact with sim.reduced.exact_modes), each measured as validate_fem measures it."""
    fem = drone.fem
    fb = balanced(fem, fixed_load(drone, gravity, load))
    full = bend_and_compliance(drone, fb, static_displacement(fem, fb))
    from sdexp.sim.reduced.body import reduced_stiffness
    u = (model.Phi @ np.linalg.solve(reduced_stiffness(model), model.Phi.T @ fb.ravel())).reshape(fem.rest.shape)
    red = bend_and_compliance(drone, fb, u)
    return {f"{k}_error": red[k] / full[k] - 1 if np.isfinite(full[k]) and full[k] != 0 else float("nan")
            for k in ("bend", "compliance")}
