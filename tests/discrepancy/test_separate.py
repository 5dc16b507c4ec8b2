"""Telling tied candidates apart (sdexp.discrepancy.separate): the signature cosine, the
manoeuvre scores flown with each candidate's physics on the same plan and noise, and the advice."""
import numpy as np
import pytest

from sdexp.discrepancy import separate


def test_alike_is_the_cosine_of_the_two_changes():
    a = np.arange(12.0).reshape(3, 4)
    assert separate.alike(a, 3 * a) == pytest.approx(1.0)
    assert separate.alike(a, -a) == pytest.approx(-1.0)
    assert separate.alike(np.array([1.0, 0.0]), np.array([0.0, 2.0])) == 0.0
    assert separate.alike(np.zeros(3), a.ravel()[:3]) == 0.0


def channels(drone) -> int:
    return 2 * drone.dim + 2 * (3 if drone.dim == 3 else 1) + 2 * drone.layout.n_s   # p, e, s and their rates


def scores(small_cfg, leaf, a, b, kinds):
    r = small_cfg.discrepancy.record
    return separate.manoeuvre_scores(leaf, small_cfg.sim, small_cfg.noise, a, b, np.ones(channels(leaf)), 1.0, 3,
                                     float(r.height), float(r.ground), float(r.amplitude), kinds=kinds)


def test_the_same_physics_flies_the_same_log_and_an_effect_shows(small_cfg, leaf):
    """Both flights of a kind share plan, noise and pilot, so only the physics can part them:
    the same effects give 0 exactly, a lost rotor gives more than nothing."""
    same = scores(small_cfg, leaf, [], [], ["hover", "differential"])
    assert same == {"hover": 0.0, "differential": 0.0}
    lost = [{"name": "thrust_loss", "rotor": 0, "fraction": 0.5}]
    apart = scores(small_cfg, leaf, lost, [], ["hover", "differential"])
    assert min(apart.values()) > 0


def test_the_advice_names_the_manoeuvre_that_separates_most():
    text = separate.advice("payload", "thrust_loss", 0.97, {"hover": 0.2, "steps": 0.5, "differential": 3.0},
                           ["hover", "steps"])
    assert "payload and thrust_loss change these flights alike (cosine 0.97)" in text
    assert "'differential' manoeuvre (not among discrepancy.record.manoeuvres)" in text and "3x the noise floor" in text
    assert "at most 0.5x" in text


def test_the_workflow_reports_a_tie_only_when_the_signatures_are_alike(small_cfg, leaf):
    """workflow._confusable: a tied candidate whose change to the held-out predictions is the
    winner's (scaled) gets the cosine, the scores of every manoeuvre and the advice, logged; one
    whose change points elsewhere is a tie more flights can settle: its cosine, no advice."""
    from dataclasses import replace
    from types import SimpleNamespace

    from sdexp.discrepancy.record import MANOEUVRES
    from sdexp.discrepancy.workflow import _confusable

    rng = np.random.default_rng(0)
    held = rng.normal(size=(5, 4, channels(leaf)))
    sigma = np.ones((4, channels(leaf)))
    lost = [{"name": "thrust_loss", "rotor": 0, "fraction": 0.5}]
    fit = lambda name, change, effects: SimpleNamespace(name=name, effects=effects,  # noqa: E731
                                                        evidence={"held_residual": held - change})
    d = rng.normal(size=held.shape)
    best = fit("thrust_loss", d, lost)
    twin = fit("payload", 2 * d, [])
    other = fit("quadratic_drag", rng.normal(size=held.shape), [])
    dcfg = replace(small_cfg.discrepancy, record=replace(small_cfg.discrepancy.record, seconds=1.0))
    said = []
    out = _confusable(best, [twin, other], held, sigma, [], leaf, small_cfg.sim, small_cfg.noise, dcfg, 3, said.append)
    assert [o["candidates"] for o in out] == [["thrust_loss", "payload"], ["thrust_loss", "quadratic_drag"]]
    assert out[0]["cosine"] == pytest.approx(1.0) and set(out[0]["manoeuvre_scores"]) == set(MANOEUVRES)
    assert out[0]["alike"] and not out[1]["alike"] and abs(out[1]["cosine"]) < 0.5 and "advice" not in out[1]
    assert said[0] == f"discrepancy: {out[0]['advice']}" and "more flights would settle it" in said[1]
