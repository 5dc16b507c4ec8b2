"""Spawned workers end with the process that started them (a killed run leaves no orphans)."""
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_workers_exit_when_their_parent_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(f"""
        import os, time
        from sdexp.parallel import run_spawned

        def task(path, report):
            open(path, "w").write(str(os.getpid()))
            time.sleep(60)

        if __name__ == "__main__":
            run_spawned(task, [(r"{tmp_path / 'child.pid'}",)], workers=1)
    """))
    parent = subprocess.Popen([sys.executable, str(script)])
    pid_file = tmp_path / "child.pid"
    for _ in range(600):
        if pid_file.exists() and pid_file.read_text():
            break
        time.sleep(0.1)
    child = int(pid_file.read_text())
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    for _ in range(100):                         # the watcher polls every second
        if not os.path.exists(f"/proc/{child}") or "zombie" in open(f"/proc/{child}/status").read().lower():
            break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the worker outlived its killed parent by 10 s")
