"""The live view in a real headless browser (Playwright + Debian's chromium) against a demo.

The demo runs as real processes (relay, remote and local stations) with the local station's
view on; chromium opens the page as a person would and the test waits for what a person
would see: the pins change, the trajectory grows, findings appear, the latency chart moves;
then the relay's page for observers (with the observer token the demo prints) shows the
patch and the trajectory, and without the token it is refused.
A screenshot is kept: in ``$TELETOUCH_TEST_ARTIFACTS`` when set, else in pytest's tmp dir
(the path is printed).

chromium comes from the distribution (``apt-get install chromium``; ``.ci/run`` installs
it), never from Playwright's own download. Without it (or without the ``playwright``
package) the test is skipped on a developer's machine and FAILS under ``CI=true``.
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
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support import REPO_ROOT, free_tcp_port, scaled, wait_until

pytestmark = pytest.mark.slow


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def _chromium() -> str:
    path = os.environ.get("TELETOUCH_CHROMIUM") or shutil.which("chromium") \
        or shutil.which("chromium-browser")
    if path:
        return path
    message = ("chromium not found (install it with `apt-get install -y chromium`; "
               ".ci/run does) - the live-view browser test cannot run")
    if _in_ci():
        pytest.fail(message)
    pytest.skip(message)


def _playwright() -> Any:
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as err:
        message = f"playwright is not installed (pip install -e '.[test]'): {err}"
        if _in_ci():
            pytest.fail(message)
        pytest.skip(message)
    return sync_playwright


def _page_up(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=1.0) as resp:
            return bool(resp.status == 200)
    except OSError:
        return False


def _relay_url(log: Path) -> str | None:
    for line in log.read_text(errors="replace").splitlines():
        if line.startswith("live view (relay, for observers): "):
            return line.split(": ", 1)[1].strip()
    return None


@pytest.fixture
def demo_view(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """A demo session with its live views on; yields the station's and the relay's URLs."""
    port = free_tcp_port()
    log = (tmp_path / "demo.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "lab.cli", "demo", "--headless", "--workdir",
         str(tmp_path / "demo"), "--view", f"127.0.0.1:{port}"],
        cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/"
    try:
        wait_until(lambda: _page_up(url) or proc.poll() is not None, 90, "the demo's view")
        if proc.poll() is not None:
            pytest.fail(f"the demo ended early: {(tmp_path / 'demo.log').read_text()[-2000:]}")
        wait_until(lambda: _relay_url(tmp_path / "demo.log") is not None, 30,
                   "the relay's view URL printed")
        yield url, str(_relay_url(tmp_path / "demo.log"))
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # the demo stops its children on the way out
            try:
                proc.wait(scaled(30))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()


def _canvas_signature(page: Any, canvas_id: str) -> int:
    """A cheap checksum of what a canvas shows now."""
    return int(page.evaluate(
        """(id) => { const c = document.getElementById(id);
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
             let h = 0; for (let i = 0; i < d.length; i += 7) h = (h * 31 + d[i]) | 0;
             return h; }""", canvas_id))


def _view(page: Any) -> dict[str, Any]:
    return dict(page.evaluate(
        """() => ({messages: teletouchView.messages, pins: teletouchView.pinUpdates,
                   trail: teletouchView.trail.length, latency: teletouchView.latencySamples,
                   findings: document.querySelectorAll('#findings li').length,
                   kinds: [...document.querySelectorAll('#findings li')].map(
                       li => li.dataset.kind)})"""))


def test_the_live_view_shows_a_running_demo(demo_view: tuple[str, str],
                                            tmp_path: Path) -> None:
    station_url, relay_url = demo_view
    chromium = _chromium()
    sync_playwright = _playwright()
    artifacts = Path(os.environ.get("TELETOUCH_TEST_ARTIFACTS") or tmp_path)
    artifacts.mkdir(parents=True, exist_ok=True)
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                     args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 900})
            page.on("pageerror", lambda err: errors.append(str(err)))
            page.goto(station_url)
            page.wait_for_function("() => window.teletouchView && teletouchView.messages > 5",
                                   timeout=scaled(30) * 1e3)
            # the relay's page for observers: patch and trajectory from the routed messages
            observer = browser.new_page(viewport={"width": 1600, "height": 900})
            observer.on("pageerror", lambda err: errors.append(f"relay page: {err}"))
            observer.goto(relay_url)
            observer.wait_for_function(
                "() => teletouchView.messages > 5 && teletouchView.trail.length > 5"
                " && teletouchView.live && teletouchView.live.patch",
                timeout=scaled(30) * 1e3)
            observer_station = observer.evaluate("() => teletouchView.live.station")
            observer.screenshot(path=str(artifacts / "live_view_relay.png"), full_page=True,
                                timeout=scaled(60) * 1e3)
            # without the token the relay refuses the page's WebSocket
            refused = browser.new_page()
            refused.goto(relay_url.split("#", 1)[0])
            refused.wait_for_function(
                "() => document.getElementById('conn').textContent.includes('refused')",
                timeout=scaled(30) * 1e3)
            observer.close()
            refused.close()
            first = _view(page)
            pins0 = _canvas_signature(page, "pins")
            lat0 = _canvas_signature(page, "chart-latency")
            # pins change, the trajectory grows, the latency chart moves
            page.wait_for_function(
                f"""() => teletouchView.pinUpdates >= {first['pins'] + 10}
                       && teletouchView.trail.length >= {first['trail'] + 20}
                       && teletouchView.latencySamples >= {first['latency'] + 10}""",
                timeout=scaled(60) * 1e3)
            wait_until(lambda: _canvas_signature(page, "pins") != pins0, 30, "the pins redrawn")
            wait_until(lambda: _canvas_signature(page, "chart-latency") != lat0, 30,
                       "the latency chart moved")
            # findings appear once the operator has palpated a tumor
            page.wait_for_selector("#findings li", timeout=scaled(150) * 1e3)
            seen = _view(page)
            time.sleep(0.5)  # let the page draw the finding before the picture is taken
            shot = artifacts / "live_view.png"
            page.screenshot(path=str(shot), full_page=True, timeout=scaled(60) * 1e3)
            print(f"live view screenshot: {shot}; state {seen}")
            badge = page.text_content("#link")
        finally:
            with contextlib.suppress(Exception):
                browser.close()
    assert seen["findings"] >= 1 and set(seen["kinds"]) <= {"benign", "malignant", "uncertain"}
    assert seen["trail"] > first["trail"] and seen["pins"] > first["pins"]
    assert badge is not None and "link" in badge
    assert shot.stat().st_size > 10_000
    assert observer_station == "relay"
    assert errors == [], f"page errors: {errors}"
