"""The candidate effects the workflow fits: library effects and a user's own, one protocol.

Every candidate comes from the effect class's own declaration (``fit_spec`` or ``fit_params``,
sdexp.sim.physics.effects.FitSpec): its parameters theta with physical bounds, theta = 0 the
nominal simulator (or ``base``). The library parametrises so that the predicted channels move
about linearly in theta over the strengths that matter (ground effect in R^2, stiffness as a
compliance change, wind as the dynamic-pressure vector |w| w, payload as mass and first
moments): one finite-difference Jacobian then fits well, and a second Gauss-Newton step
(chord) corrects what is left. Where no parametrisation is near-linear over the range
(stiffness: its strong changes shift the bending frequencies, so the predicted oscillations
move out of phase; a delay shifts whole responses in time) a coarse ``scan`` of theta values
picks where the finite differences are taken. ``options`` are discrete choices fitted by
enumeration (which rotor lost thrust).

``discrepancy.candidates`` lists library names and ``{_target_: package.module.Class, ...}``
entries alike; an entry's other keys are fixed constructor arguments (not fitted).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from sdexp.errors import UserError
from sdexp.sim.physics.effects import LIBRARY, Effect, resolve_effect


@dataclass
class Candidate:
    name: str
    params: list[str]                    # fitted parameters (the theta the fit reports)
    steps: np.ndarray                    # finite-difference steps: typical strengths
    lower: np.ndarray                    # physical bounds
    upper: np.ndarray
    build: Callable                      # (theta, option) -> list of effect entries
    report: Callable                     # (theta, option) -> dict of physical parameters
    options: list = field(default_factory=lambda: [None])
    base: Callable | None = None         # option -> entries at theta = 0 when not nominal
    anchor: np.ndarray | None = None     # where the other columns are differenced (payload: a mass)
    scan: list | None = None             # theta values tried first; the best is linearised about
    memory: float = 0.0                  # s of past commands a window must replay for it
    check: Callable | None = None        # (theta, option) -> why a fit is not physical, or None
    strength: list[int] | None = None    # the theta components that say whether it is there at all (None: all)

    def flags(self, theta: np.ndarray, option) -> list[str]:
        """Why a fit at theta cannot be accepted: a parameter on a physical bound other than its
        nominal 0 (the data asked for more than physics allows), or the effect's own check."""
        out = []
        for j, name in enumerate(self.params):
            for bound, side in ((self.lower[j], "lower"), (self.upper[j], "upper")):
                if bound != 0 and abs(theta[j] - bound) <= 1e-6 * max(1.0, abs(bound)):
                    out.append(f"{name} at its {side} bound {bound:g}")
        why = self.check(theta, option) if self.check else None
        return out + ([why] if why else [])


# {candidate: its strength's fitted parameters} where not every theta is one (Candidate.strength):
# a payload is there by its mass; its first moments say where it sits, and a fit off the centre
# moves them off 0 however uncertain the mass (converged flower, strong gusty wind: a second
# effect's mass profiled at 0 to 0.37 kg)
STRENGTH = {"payload": ("mass",)}


def candidate(entry, drone) -> Candidate | None:
    """The candidate of one ``discrepancy.candidates`` entry (a library name or a ``_target_``
    dict), or None when the effect does not apply to this drone (a 2D rotor has no spin axis)."""
    cls, fixed, head = resolve_effect(entry, "discrepancy.candidates")
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise UserError(f"discrepancy.candidates: {head} is not an sdexp.sim.physics.effects.Effect")
    spec = cls.fit_spec(drone)
    if spec is None:
        if "_target_" in head and not cls.fit_params:
            raise UserError(f"discrepancy.candidates: {head['_target_']} declares nothing to fit: give the class "
                            f"fit_params = {{argument: (lower, upper, step)}} or a fit_spec classmethod "
                            f"(docs/discrepancy_workflow.md)")
        return None
    name = head.get("name") or getattr(cls, "name", None) or cls.__name__
    for q, lo, hi in zip(spec.params, spec.lower, spec.upper):
        if not lo <= 0 <= hi:
            raise UserError(f"discrepancy.candidates: {name}.{q} bounds [{lo}, {hi}] exclude its nominal 0 "
                            f"(theta = 0 must be the simulator without the effect)")
    kwargs = lambda th, o: {**head, **fixed, **spec.entry(np.asarray(th, dtype=float), o)}  # noqa: E731
    report = spec.report or spec.entry
    base = None
    if spec.base is not None:
        base = lambda o: [{**head, **fixed, **spec.base(o)}]  # noqa: E731
    elif "_target_" in head:
        # a user's effect at theta = 0 is what its declaration says is nothing; trust it only
        # as far as a rollout shows: the reference is the effect at theta = 0, not the nominal
        base = lambda o: [kwargs(np.zeros(len(spec.params)), o)]  # noqa: E731
    a = lambda v: None if v is None else np.asarray(v, dtype=float)  # noqa: E731
    strength = [list(spec.params).index(q) for q in STRENGTH[name]] if name in STRENGTH else None
    return Candidate(name, list(spec.params), a(spec.steps), a(spec.lower), a(spec.upper),
                     lambda th, o: [kwargs(th, o)], lambda th, o: report(np.asarray(th, dtype=float), o),
                     list(spec.options), base, a(spec.anchor),
                     None if spec.scan is None else [a(t) for t in spec.scan], float(spec.memory), spec.check, strength)


def library_candidates(drone, entries=None) -> list[Candidate]:
    """Candidates for ``entries`` (names and ``_target_`` dicts); None or [] = the whole library.
    A library effect that does not apply to the drone is left out when the library is implied
    and an error when named."""
    if not entries:
        return [c for c in (candidate(n, drone) for n in LIBRARY) if c is not None]
    out = []
    for e in entries:
        c = candidate(e, drone)
        if c is None:
            raise UserError(f"discrepancy.candidates: {e} does not apply to the {drone.dim}D drone {drone.name}")
        out.append(c)
    return out


def history_seconds(cands: list[Candidate], floor: float) -> float:
    """Seconds of past commands each window replays: ``floor`` (discrepancy.history) or what
    the slowest candidate needs, whichever is longer. From a zero actuator state a slow lag
    predicts worse than no lag at all, and its fit comes out too short."""
    return max([float(floor)] + [c.memory for c in cands])
