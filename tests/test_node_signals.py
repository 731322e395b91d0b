"""A node process ends on SIGTERM with status 143 and its ``finally`` blocks run, without a
traceback on the console also when the signal lands in a finalizer (a bus's ``__del__``, seen
when a full disk ended a run: "Exception ignored in: BusABC.__del__ ... SystemExit: 143")."""
from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import os, signal, time
from canbrake.run import node_signals
node_signals()
class Bus:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)  # the orchestrator's SIGTERM, while a finalizer runs
        sum(range(1000))
try:
    b = Bus(); del b
    time.sleep(2.0)
    print("still running")
finally:
    print("finally ran")
"""


def test_sigterm_in_a_finalizer_ends_the_node_quietly_with_143() -> None:
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60)
    assert r.returncode == 143, (r.returncode, r.stderr)
    assert r.stdout.strip() == "finally ran"
    assert "Traceback" not in r.stderr and "Exception ignored" not in r.stderr, r.stderr
