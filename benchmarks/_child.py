"""Run a benchmark script again as a child process (its own memory and CPU accounts)."""
from __future__ import annotations

import json
import subprocess
import sys


def spawn(script: str, args: list[str]) -> dict:
    """Run ``python script *args``; return the JSON object it prints on its last line.

    Raises
    ------
    RuntimeError
        With the end of the child's stderr, when it exits non-zero.
    """
    proc = subprocess.run([sys.executable, script, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"child {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
