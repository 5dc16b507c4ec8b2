"""When candidates explain the measured flights alike (a tie), say so and name the manoeuvre
that would tell them apart.

``alike``: the cosine between what two fitted candidates change in the held-out predictions
(each residual change over the noise floor, all windows and channels as one vector); 1 is the
same signature. ``manoeuvre_scores``: one short flight per manoeuvre kind of the recorder
(``record.MANOEUVRES``), flown twice with the same plan, noise and pilot, once with each
candidate's fitted effects; the score is the RMS over time and channels of the two logs'
difference over the noise floor (per channel, the workflow's sigma averaged over the horizon).
The kind with the largest score separates the two most; a kind the measured set lacks is
worth recording.
"""
from __future__ import annotations

import numpy as np

ALIKE = 0.9   # cosine above which two fitted candidates read as one signature on these flights


def alike(change_a: np.ndarray, change_b: np.ndarray) -> float:
    """Cosine of two residual changes (any shape, already over the noise floor)."""
    a, b = np.ravel(change_a), np.ravel(change_b)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else 0.0


def manoeuvre_scores(drone, sim_cfg, noise_cfg, effects_a: list, effects_b: list, scale: np.ndarray,
                     seconds: float, seed: int, height: float, ground: float, amplitude: float,
                     kinds=None) -> dict[str, float]:
    """manoeuvre kind -> RMS of (log with effects_a - log with effects_b) / scale (per channel)."""
    from sdexp.discrepancy.record import MANOEUVRES, manoeuvre_log

    out = {}
    for kind in kinds or MANOEUVRES:
        logs = [manoeuvre_log(drone, sim_cfg, noise_cfg, effects, kind, seconds, seed, height, ground, amplitude)
                for effects in (effects_a, effects_b)]
        n = min(len(logs[0]), len(logs[1]))
        out[kind] = float(np.sqrt(np.mean(((logs[0][:n] - logs[1][:n]) / scale) ** 2))) if n else float("nan")
    return out


def advice(a: str, b: str, cosine: float, scores: dict[str, float], recorded) -> str:
    """One line for the log and the report."""
    best = max(scores, key=lambda k: scores[k])
    recorded = list(recorded)
    have = max((scores[k] for k in recorded if k in scores), default=float("nan"))
    new = "" if best in recorded else " (not among discrepancy.record.manoeuvres)"
    return (f"{a} and {b} change these flights alike (cosine {cosine:.2f}): the flights cannot tell them "
            f"apart. Record the '{best}' manoeuvre{new}: there the two differ by {scores[best]:.2g}x the "
            f"noise floor" + (f", in the recorder's kinds by at most {have:.2g}x" if have == have else ""))
