"""The command line of a child process running one of this project's modules.

``python -m MODULE`` puts the working directory first on ``sys.path``, so a ``shared/`` or
``lab/`` directory there shadows the installed packages: run from the directory that holds
the repository and the team kit beside it (``../shared``), ``teletouch demo`` started its
children against the kit's ``shared/`` and failed at once. ``-P`` (Python 3.11+) leaves the
working directory off ``sys.path``; ``PYTHONPATH`` still applies (``bench relay-cpu`` points
it at another revision's tree).
"""

from __future__ import annotations

import sys

__all__ = ["module_argv"]


def module_argv(module: str = "lab.cli", python: str = sys.executable) -> list[str]:
    """``[python, "-P", "-m", module]``: the start of a child's command line."""
    return [python, "-P", "-m", module]
