"""Simulator: one ``step(u)`` advances one control interval (10 ms) in explicit substeps and
returns the (noisy, as configured) IMU readings. An episode that blows up ends with a recorded
failure reason; nothing raises.

Actuation: the command is clipped to [-max_thrust, max_thrust], held back by the output delay
(a FIFO of whole control steps), perturbed by Gaussian rotor noise, and applied along each
rotor patch's current surface normal for the whole interval.

Effects (``sim.effects``, sdexp.sim.physics.effects) hook in at the model (mass, stiffness, damping),
the actuators (after the rotor noise), the body (external forces held over the control step)
and the sensors (before the sensor noise). With no effects the step is what it was.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numba
import numpy as np

from sdexp.errors import UserError
from sdexp.sim.drone import Drone
from sdexp.sim.physics.effects import build_effects, overrides
from sdexp.sim.physics.fem import stable_substep
from sdexp.sim.physics.integrator import Body, extent
from sdexp.sim.physics.modes import mass_scaling
from sdexp.sim.physics.native import default_cache_dir
from sdexp.sensing import Readings, decompose, State
from sdexp.sim.sensors import add_noise, read_imus

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from sdexp.config import NoiseConfig, SimConfig


# Below this many linear elements' work a second thread saves no more than its synchronisation
# costs (three barriers a substep; measured again in session 6 on 542-1328 elements: a wash
# within this VM's noise), and a busy second core stalls every barrier. A quadratic tet is about
# four linear ones of work (kernels.c: 115 against 25 ns here).
PARALLEL_MIN_ELEMENTS = 1500
QUADRATIC_WORK = 4


@dataclass
class Failure:
    reason: str      # inverted_element | non_finite | runaway_speed | runaway_extent | left_reduced_range
    time: float      # survival time (s)
    detail: str = ""


class _Full:
    """sim.model = full, as the simulator sees it: the FEM body (sdexp.sim.physics.integrator.Body),
    read and placed through its vertices' x and v alone, so that an earlier commit's Body steps here
    too (the bitwise test, sdexp.eval.bench_kernels)."""

    reduced = None

    def __init__(self, sim: "Simulator"):
        self.sim = sim
        self.imus = sim.drone.imus

    def stable_substep(self, safety: float, inertia) -> float:
        return stable_substep(self.sim.fem, safety, mass=inertia)

    def body(self):
        sim, c = self.sim, self.sim.cfg
        boxes = list(c.obstacles)
        return Body(sim.fem, sim.threads, sim.drone.rotors, c.ground,
                    [list(b.min) for b in boxes] or None, [list(b.max) for b in boxes] or None,
                    c.friction, precision=c.precision, added_mass=sim.scaling.added)

    def nodes(self, body) -> tuple[np.ndarray, np.ndarray]:
        """What the IMUs read: every vertex (``imus.idx`` indexes the mesh)."""
        return body.x, body.v

    def translate(self, body, offset: np.ndarray) -> None:
        body.x += offset

    def place(self, body, x, v, rotation) -> None:
        from sdexp.sensing.rotations import quat_from_matrix
        body.x[:] = x
        body.v[:] = v
        if rotation is not None and self.sim.drone.dim == 3:
            body.set_rotation(quat_from_matrix(np.asarray(rotation)))

    def save(self, body):
        return body.x.copy(), body.v.copy()

    def restore(self, body, saved) -> None:
        body.x[:], body.v[:] = saved

    def size(self, body) -> float:
        return extent(body.x)

    def left_range(self, body) -> str | None:
        return None   # the full model has no fitted range


class _Reduced:
    """sim.model = reduced, as the simulator sees it: a ReducedBody (floating frame and modal
    coordinates, sdexp.sim.reduced.body) of the drone's reduced model."""

    def __init__(self, sim: "Simulator", reduced):
        self.sim, self.reduced = sim, reduced
        self.imus = replace(sim.drone.imus, idx=reduced.imu_idx)   # the patches' nodes, in the model's own order

    def stable_substep(self, safety: float, inertia) -> float:
        from sdexp.sim.reduced.body import stable_substep as reduced_substep
        return reduced_substep(self.reduced, safety)

    def body(self):
        from sdexp.sim.reduced.body import ReducedBody
        body = ReducedBody(self.reduced, self.sim.cfg.precision)
        body.pushed = bool(self.sim._push)
        return body

    def nodes(self, body) -> tuple[np.ndarray, np.ndarray]:
        """What the IMUs read: the patches' nodes only, not the whole mesh."""
        x, v, _ = body.sensor_nodes()
        return x, v

    def translate(self, body, offset: np.ndarray) -> None:
        body.translate(offset)

    def place(self, body, x, v, rotation) -> None:
        body.set_full(x, v)   # the frame is the best fit of x: no rotation to warm-start

    def save(self, body):
        return body.copy_state()

    def restore(self, body, saved) -> None:
        body.restore(saved)

    def size(self, body) -> float:
        # bounded by the range check (its mesh is not rebuilt a step): only finiteness is asked
        return 0.0 if np.all(np.isfinite(body.z)) else np.nan

    def left_range(self, body) -> str | None:
        """Why the flight left the range the model was fitted on, or None."""
        out = body.outside()
        if out < 0:
            return None
        r = self.reduced
        return (f"modal coordinate {out} = {body.z[out]:.4g} left the range the reduced model was fitted on "
                f"[{r.z_lo[out]:.4g}, {r.z_hi[out]:.4g}] (sim.reduced.range_margin x the snapshots')")


class Simulator:
    def __init__(self, drone: Drone, sim_cfg: SimConfig, noise_cfg: NoiseConfig, seed: int = 0, effects=None,
                 draws: bool = True):
        """``effects``: Effect objects or entries; None = the ``sim.effects`` list. ``draws``
        False: random effects take their expectation (``start`` gets no generator), as a
        predictor that cannot know a flight's gusts should."""
        self.draws = draws
        self.drone = drone
        self.cfg = sim_cfg
        self.noise = noise_cfg
        self.rng = np.random.default_rng(seed)
        self.effects = build_effects(getattr(self.cfg, "effects", []) if effects is None else effects)
        self.fem, damping = drone.fem, drone.damping
        for e in self.effects:
            self.fem, damping = e.modify_model(self.fem, damping, drone)
        # None: read drone.damping at every step (callers may change it after construction)
        self._damping = damping if any(overrides(e, "modify_model") for e in self.effects) else None
        self._act = [e for e in self.effects if overrides(e, "actuate")]
        self._push = [e for e in self.effects if overrides(e, "body_forces")]
        self._sense = [e for e in self.effects if overrides(e, "sense")]
        fem, c, n = self.fem, self.cfg, self.noise
        # the one place the two models part: everything below asks self.model
        self.model = _Reduced(self, self._reduced_model()) if getattr(c, "model", "full") == "reduced" else _Full(self)
        self.reduced = self.model.reduced   # the reduced model, or None (the privileged controller reads it)
        self.scaling = mass_scaling(fem, c.mass_scaling, default_cache_dir())
        if c.mass_scaling > 0 and self.scaling.added is None:
            log.warning(f"sim.mass_scaling = {c.mass_scaling:g}: no step gain for drone {drone.name} within this "
                        f"budget (the first rung, x1.05, needs more added mass); running unscaled")
        inertia = fem.mass if self.scaling.added is None else fem.mass + self.scaling.added
        dt_stable = self.model.stable_substep(c.stability_safety, inertia)
        if not (np.isfinite(dt_stable) and dt_stable > 0):
            raise UserError(f"drone {drone.name}: no stable explicit substep for its mesh (largest eigenvalue of "
                            f"M^-1 K not finite and positive); change drone.mesh (edge_length / layers)")
        dt_max = c.substep if c.substep is not None else dt_stable
        self.n_sub = int(np.ceil(c.control_dt / dt_max - 1e-9))
        self.dt = c.control_dt / self.n_sub
        work = fem.n_elems * (QUADRATIC_WORK if fem.order == 2 else 1)
        self.threads = c.threads or (2 if work >= PARALLEL_MIN_ELEMENTS else 1)
        self.threads = min(self.threads, numba.config.NUMBA_NUM_THREADS)
        self._delay_steps = int(round(n.delay / c.control_dt)) if n.enabled else 0
        self._rest_extent = extent(fem.rest)
        self._start = [e for e in self.effects if overrides(e, "start")]
        self.seed, self.flight = seed, -1
        self._new_body()   # setup may read the body (rest pose, vertex sets)
        for e in self.effects:
            e.setup(self)
        self.reset()

    def _reduced_model(self):
        """sim.model = reduced: the drone's reduced model (built or cached), after refusing what
        it cannot carry: contact, mass scaling, effects that change the model."""
        from sdexp.sim.reduced.model import build_reduced, spec_of
        c = self.cfg
        refuse = [("sim.ground", c.ground is not None, "a ground plane (contact acts on every node)"),
                  ("sim.obstacles", bool(c.obstacles), "obstacles (contact acts on every node)"),
                  ("sim.mass_scaling", c.mass_scaling > 0, "mass scaling (decided off; the basis sets the step)")]
        refuse += [(f"sim.effects: {type(e).__name__}", self.fem is not self.drone.fem,
                    "an effect that changes the FEM model (mass or stiffness): the basis was fitted on the drone's own")
                   for e in self.effects if overrides(e, "modify_model")]
        for key, bad, what in refuse:
            if bad:
                raise UserError(f"sim.model = reduced cannot carry {what} ({key}); run it with sim.model=full")
        return build_reduced(self.drone, spec_of(c.reduced), str(default_cache_dir()),
                             c.gravity, c.control_dt)

    # -------------------------------------------------------------------------------- state
    def _new_body(self) -> None:
        self.body = self.model.body()
        self.t = 0.0
        self.failure: Failure | None = None
        self.applied = np.zeros(self.drone.num_rotors)
        self._queue = deque([np.zeros(self.drone.num_rotors)] * self._delay_steps)

    def reset(self, position=None, flight: int | None = None) -> Readings:
        """A new flight: the undeformed drone at rest, moved by ``position``. Effects draw their
        random parts for it (``start``) from a generator seeded by (simulator seed, flight
        index): the next index unless ``flight`` is given, so a recorder that names its flights
        gets the same draws whatever ran before."""
        self._new_body()
        if position is not None:
            self.model.translate(self.body, np.asarray(position, dtype=float))
        self.flight = self.flight + 1 if flight is None else int(flight)
        if self._start:
            rng = np.random.default_rng([abs(int(self.seed)), self.flight]) if self.draws else None
            for e in self._start:
                e.start(self, rng)
        for e in self.effects:
            e.reset(self)
        return self.readings()

    def set_state(self, x, v, rotation=None, t: float = 0.0, history=()) -> None:
        """Re-initialise within the current flight from a given state: vertex positions and
        velocities, the element rotations warm-started at ``rotation`` (3x3, 3D; else identity),
        and the actuation chain (output delay, effect states such as motor lag) replayed with the
        past commands ``history`` (oldest first) without moving the body. Effects keep their
        flight's draws (a gust sequence is a function of time) and only ``reset``."""
        self._new_body()
        self.model.place(self.body, x, v, rotation)
        self.t = float(t)
        for e in self.effects:   # after the state is set: an effect may start from it
            e.reset(self)
        for u in history:
            self.applied = self._actuate(u, noisy=False)

    @property
    def damping(self) -> float:
        return self.drone.damping if self._damping is None else self._damping

    @property
    def alive(self) -> bool:
        return self.failure is None

    @property
    def x(self) -> np.ndarray:
        """Vertex positions (nv, dim): for plots and tests; controllers see readings only."""
        return self.body.x

    @property
    def v(self) -> np.ndarray:
        return self.body.v

    def readings(self, noisy: bool = True) -> Readings:
        x, v = self.model.nodes(self.body)
        r = read_imus(self.t, x, v, self.model.imus)
        for e in self._sense:  # a sensor's systematic error is part of what it reads
            r = e.sense(r, self)
        return add_noise(r, self.noise, self.rng) if noisy else r

    def state(self, noisy: bool = True) -> State:
        return decompose(self.readings(noisy), self.drone.layout)

    @property
    def thrust_directions(self) -> np.ndarray:
        """Unit thrust direction of every rotor during the last substep."""
        return self.body.dirs.copy()

    # -------------------------------------------------------------------------------- step
    def step(self, u) -> Readings:
        """Advance one control interval with command u; returns the readings after it.
        After a failure the state is frozen and the same readings come back."""
        if self.failure is not None:
            return self.readings()
        cmd = self._actuate(u, noisy=True)
        self.applied = cmd
        if self._push:
            f = self.body.fext
            f[:] = 0.0
            for e in self._push:
                e.body_forces(self, f)
        self._advance(cmd)
        return self.readings()

    def _actuate(self, u, noisy: bool) -> np.ndarray:
        """Commanded -> applied thrust: clip, output delay, rotor noise, actuator effects."""
        tmax = self.drone.max_thrust
        cmd = np.clip(np.asarray(u, dtype=float), -tmax, tmax)
        if self._delay_steps:
            self._queue.append(cmd)
            cmd = self._queue.popleft()
        if noisy and self.noise.enabled and self.noise.rotor_std > 0:
            cmd = cmd + self.rng.normal(0.0, self.noise.rotor_std, cmd.shape)
        for e in self._act:
            cmd = e.actuate(cmd, self)
        return cmd

    def _advance(self, thrust: np.ndarray) -> None:
        body, model = self.body, self.model
        before = model.save(body)   # the last sane state, kept for the readings after a failure
        inverted, vmax2 = body.run(self.n_sub, self.dt, thrust, self.damping, self.cfg.gravity,
                                   self.drone.deformation_damping)
        self.t += self.cfg.control_dt
        reason = None
        size = model.size(body)
        left = model.left_range(body)   # its range first: what follows, follows from it
        if not (np.isfinite(vmax2) and np.isfinite(size)):
            reason, detail = "non_finite", "positions or velocities are not finite"
        elif left is not None:
            reason, detail = "left_reduced_range", left
        elif inverted > 0:
            reason, detail = "inverted_element", f"{inverted} elements inverted"
        elif vmax2 > self.cfg.max_speed ** 2:
            reason, detail = "runaway_speed", f"vertex speed {np.sqrt(vmax2):.1f} m/s > sim.max_speed"
        elif size > self.cfg.max_stretch * self._rest_extent:
            reason, detail = "runaway_extent", "body stretched beyond sim.max_stretch x its rest size"
        if reason is not None:
            self.failure = Failure(reason, self.t, detail)
            if reason == "left_reduced_range":
                log.warning(f"sim.model = reduced, drone {self.drone.name}: the flight left the reduced model's "
                            f"validated range at t = {self.t:.2f} s ({detail}); ended as a failure")
            model.restore(body, before)
