"""What the browser tests of the live view share: chromium, Playwright, a page, the process.

chromium comes from the distribution (``apt-get install chromium``; ``.ci/run`` installs
it), never from Playwright's own download; Playwright drives it through
``executable_path``. Without chromium or the ``playwright`` package a test is skipped on a
developer's machine and FAILS under ``CI=true``.

* :func:`headless_browser` (and the ``browser`` fixture of ``tests/lab/conftest.py``): a
  launched chromium whose pages record their errors, and the directory for screenshots
  (``$TELETOUCH_TEST_ARTIFACTS`` when set, else pytest's tmp dir);
* :func:`page_up`: the view's page answers;
* :func:`start_cli` / :func:`interrupt`: a ``teletouch`` command in its own process group,
  ended the way a person ends it (SIGINT, Ctrl-C) with every wait bounded; when it does not
  exit in time the whole group (its children too) is killed, never waited on without end.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import pytest

from tests.support import REPO_ROOT, scaled

VIEWPORT = {"width": 1600, "height": 900}


def in_ci() -> bool:
    """The environment says ``CI=true``: missing browser tools fail instead of skipping."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def chromium_path() -> str:
    """Debian's chromium (``$TELETOUCH_CHROMIUM`` first); skips, or fails under CI."""
    path = os.environ.get("TELETOUCH_CHROMIUM") or shutil.which("chromium") \
        or shutil.which("chromium-browser")
    if path:
        return path
    message = ("chromium not found (install it with `apt-get install -y chromium`; "
               ".ci/run does) - the live-view browser test cannot run")
    if in_ci():
        pytest.fail(message)
    pytest.skip(message)


def sync_playwright_api() -> Any:
    """``playwright.sync_api.sync_playwright``; skips, or fails under CI, without it."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as err:
        message = f"playwright is not installed (pip install -e '.[test]'): {err}"
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)
    return sync_playwright


def page_up(url: str) -> bool:
    """The page at ``url`` answers 200 now."""
    try:
        with urllib.request.urlopen(url, timeout=1.0) as resp:
            return bool(resp.status == 200)
    except OSError:
        return False


@dataclass
class Browser:
    """A headless chromium for one test.

    Attributes:
        browser: Playwright's browser.
        artifacts: where screenshots go.
        errors: every page's uncaught errors (``label: error``); a test asserts it empty.
    """

    browser: Any
    artifacts: Path
    errors: list[str] = field(default_factory=list)

    def new_page(self, label: str = "page", **kw: Any) -> Any:
        """A page of the usual size whose errors land in :attr:`errors`."""
        page = self.browser.new_page(viewport=kw.pop("viewport", VIEWPORT), **kw)
        page.on("pageerror", lambda err: self.errors.append(f"{label}: {err}"))
        return page


@contextlib.contextmanager
def headless_browser(tmp_path: Path) -> Iterator[Browser]:
    """Launch Debian's chromium through Playwright; closed on the way out."""
    chromium = chromium_path()
    sync_playwright = sync_playwright_api()
    artifacts = Path(os.environ.get("TELETOUCH_TEST_ARTIFACTS") or tmp_path)
    artifacts.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                     args=["--no-sandbox", "--disable-gpu"])
        try:
            yield Browser(browser, artifacts)
        finally:
            with contextlib.suppress(Exception):
                browser.close()


def start_cli(args: Sequence[str], log: IO[bytes], *,
              stdout: int | IO[bytes] = subprocess.PIPE) -> subprocess.Popen[bytes]:
    """``python -m lab.cli ARGS`` in a process group of its own (its children with it).

    stderr goes to ``log``; stdout to a pipe unless ``stdout`` says otherwise.
    """
    return subprocess.Popen([sys.executable, "-m", "lab.cli", *args], cwd=REPO_ROOT,
                            stdout=stdout, stderr=log, start_new_session=True)


@dataclass(frozen=True)
class Ended:
    """How a process ended after :func:`interrupt`.

    Attributes:
        stdout: what it printed (b"" when stdout was not a pipe).
        seconds: from the SIGINT to its exit (or to the kill).
        killed: it did not exit within the bound; its group was killed.
    """

    stdout: bytes
    seconds: float
    killed: bool


def interrupt(proc: subprocess.Popen[bytes], timeout_s: float = 30.0, *,
              group: bool = False) -> Ended:
    """Send SIGINT (Ctrl-C) and wait at most ``scaled(timeout_s)`` for the exit.

    ``group``: to the whole process group, as a terminal's Ctrl-C does (``proc`` must lead
    it: :func:`start_cli`). A process still there after the wait is killed with its whole
    group (a child holding its stdout would make an unbounded ``communicate()`` hang), and
    the rest read with a bound too.
    """
    t0 = time.monotonic()
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            if group:
                os.killpg(proc.pid, signal.SIGINT)
            else:
                proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=scaled(timeout_s))
        return Ended(out or b"", time.monotonic() - t0, killed=False)
    except subprocess.TimeoutExpired:
        seconds = time.monotonic() - t0
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=scaled(10))
        return Ended(out or b"", seconds, killed=True)
