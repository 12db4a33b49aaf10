"""Children started by the lab run the installed packages, not a ``shared/`` or ``lab/``
directory that happens to sit in the working directory (the team kit beside the repository
is one: ``teletouch demo`` run from the repository's parent failed at once)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from lab.child import module_argv
from tests.support import scaled

TOKEN_ARGS = ["relay", "--print-token", "s1", "--secret", "k" * 32]


def _decoys(where: Path) -> None:
    for name in ("shared", "lab"):
        (where / name).mkdir()
        (where / name / "README.md").write_text("a directory of documents, not a package\n")


def test_a_child_ignores_packages_shadowed_by_its_working_directory(tmp_path: Path) -> None:
    _decoys(tmp_path)
    plain = subprocess.run([sys.executable, "-m", "lab.cli", *TOKEN_ARGS], cwd=tmp_path,
                           capture_output=True, text=True, timeout=scaled(60.0))
    assert plain.returncode != 0  # the hazard: the decoys shadow the installed packages
    assert "shared" in plain.stderr
    fixed = subprocess.run([*module_argv(), *TOKEN_ARGS], cwd=tmp_path, capture_output=True,
                           text=True, timeout=scaled(60.0))
    assert fixed.returncode == 0, fixed.stderr
    assert len(fixed.stdout.strip()) == 64  # an HMAC token, hex
