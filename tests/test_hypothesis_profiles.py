"""The hypothesis profile comes from ``HYPOTHESIS_PROFILE`` (``tests/conftest.py``).

Each case runs a small property test in a fresh pytest process with the suite's conftest and
records what it drew: under ``ci`` two runs draw the same examples, under ``explore`` they
do not, and an unknown profile name stops the run with a message naming the profiles.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import scaled

ROOT = Path(__file__).resolve().parents[1]

PROBE = '''
import os

from hypothesis import given, settings, strategies as st


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**62))
def test_draw(n):
    with open(os.environ["PROBE_OUT"], "a") as out:
        out.write(f"{n}\\n")
'''


def _pytest(work: Path, test_file: str, source: str,
            env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """Run ``source`` as ``work / test_file`` in a fresh pytest with the suite's settings
    and conftest (applied to a test outside the suite)."""
    work.mkdir()
    (work / test_file).write_text(source)
    # hypothesis keeps its files under the working directory unless told otherwise
    inherited = {k: v for k, v in os.environ.items() if k != "HYPOTHESIS_STORAGE_DIRECTORY"}
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "-c", str(ROOT / "pyproject.toml"), "--rootdir", str(work),
                           "-p", "tests.conftest", test_file], cwd=work,
                          env={**inherited, "PYTHONPATH": str(ROOT), **env},
                          capture_output=True, text=True, timeout=scaled(120))


def _run(tmp_path: Path, profile: str,
         tag: str) -> tuple[subprocess.CompletedProcess[str], list[int]]:
    """Run the probe test under ``profile`` in ``tmp_path / tag``: the process, its draws."""
    out = tmp_path / tag / "draws.txt"
    proc = _pytest(tmp_path / tag, "test_probe.py", PROBE,
                   {"HYPOTHESIS_PROFILE": profile, "PROBE_OUT": str(out)})
    draws = [int(x) for x in out.read_text().split()] if out.exists() else []
    return proc, draws


def test_the_ci_profile_draws_the_same_examples_on_every_run(tmp_path: Path) -> None:
    first, a = _run(tmp_path, "ci", "a")
    second, b = _run(tmp_path, "ci", "b")
    assert first.returncode == 0, first.stdout + first.stderr
    assert second.returncode == 0, second.stdout + second.stderr
    assert len(a) >= 10
    assert a == b


def test_the_explore_profile_draws_new_examples_on_every_run(tmp_path: Path) -> None:
    first, a = _run(tmp_path, "explore", "a")
    second, b = _run(tmp_path, "explore", "b")
    assert first.returncode == 0, first.stdout + first.stderr
    assert second.returncode == 0, second.stdout + second.stderr
    assert len(a) >= 10 and len(b) >= 10
    assert a != b


FAILING = '''
from hypothesis import given, settings, strategies as st


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 100))
def test_fails(n):
    assert n < 50
'''


@pytest.mark.parametrize(("profile", "saved"), [("explore", False), ("ci", False),
                                                 ("dev", True)])
def test_only_the_dev_profile_saves_failing_examples(tmp_path: Path, profile: str,
                                                     saved: bool) -> None:
    # a failure under explore or ci leaves no example database behind (hypothesis keeps
    # other caches in .hypothesis, e.g. the constants it reads from local source files);
    # dev, hypothesis's default, saves the failing example to replay it
    proc = _pytest(tmp_path / profile, "test_failing.py", FAILING,
                   {"HYPOTHESIS_PROFILE": profile})
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert (tmp_path / profile / ".hypothesis" / "examples").exists() == saved


@pytest.mark.parametrize("profile", ["nightly", ""])
def test_an_unknown_profile_stops_the_run_and_names_the_profiles(tmp_path: Path,
                                                                  profile: str) -> None:
    proc, draws = _run(tmp_path, profile, "x")
    assert proc.returncode != 0
    assert draws == []
    text = proc.stdout + proc.stderr
    assert f"HYPOTHESIS_PROFILE={profile!r}" in text
    assert "dev, ci, explore" in text


def test_no_profile_has_a_deadline(tmp_path: Path) -> None:
    # an example slower than hypothesis's default 200 ms deadline passes under every profile
    # (a loaded machine must not fail a property test by the clock)
    slow = '''
import time

from hypothesis import given, settings, strategies as st


@settings(max_examples=2)
@given(st.integers(0, 10))
def test_slow(n):
    time.sleep(0.25)
'''
    for profile in ("dev", "ci", "explore"):
        proc = _pytest(tmp_path / profile, "test_slow.py", slow,
                       {"HYPOTHESIS_PROFILE": profile})
        assert proc.returncode == 0, proc.stdout + proc.stderr
