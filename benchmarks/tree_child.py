"""Run a benchmark's own ``--child`` mode with another checkout's code on the path.

A before/after benchmark calls :func:`run_in_tree` once per tree with the same JSON payload;
the child (``script --child PAYLOAD``, cwd and ``PYTHONPATH`` = the tree) prints its result as
JSON on its last line of standard output.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any


def run_in_tree(script: str | Path, tree: Path, payload: Any) -> Any:
    """``script --child json(payload)`` run with ``tree``'s code; its last JSON line.

    Raises:
        RuntimeError: the child failed (its standard error's tail in the message).
    """
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, str(Path(script).resolve()), "--child",
                           json.dumps(payload)], env=env, cwd=tree, check=False,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"the child in {tree} exited {done.returncode}:\n"
                           f"{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])
