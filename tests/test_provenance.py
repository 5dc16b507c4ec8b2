"""Every run's log names the code that made it (sdexp.provenance)."""
import subprocess

from sdexp import provenance


def test_the_source_names_the_commit_in_a_checkout_and_the_version_without_git(monkeypatch):
    provenance.source.cache_clear()
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True,
                          cwd=provenance.__file__.rsplit("/", 1)[0]).stdout.strip()
    assert f"commit {head}" in provenance.source() if head else "commit" not in provenance.source()

    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")
    monkeypatch.setattr(provenance.subprocess, "run", no_git)
    provenance.source.cache_clear()
    assert provenance.source().startswith("sdexp ") and "commit" not in provenance.source()
    provenance.source.cache_clear()


def test_a_run_logs_its_code(tmp_path, cache_dir, caplog):
    import logging

    from tests.conftest import make_cfg
    from sdexp.eval.run import run_experiment
    cfg = make_cfg("experiment=gallery", "experiment.params.drones=[rod]", f"cache_dir={cache_dir}")
    with caplog.at_level(logging.INFO):
        run_experiment(cfg, tmp_path)
    assert any("sdexp: code: sdexp " in r.getMessage() for r in caplog.records)
