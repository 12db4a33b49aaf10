"""The live view in a real headless browser (Playwright + Debian's chromium) against a demo.

The demo runs as real processes (relay, remote and local stations) with the local station's
view on; chromium opens the page as a person would and the test waits for what a person
would see: the pins change, the trajectory grows, findings appear, the latency chart moves;
then the relay's page for observers (with the observer token the demo prints) shows the
patch and the trajectory, and without the token it is refused.
A screenshot is kept: in ``$TELETOUCH_TEST_ARTIFACTS`` when set, else in pytest's tmp dir
(the path is printed).

chromium, Playwright and the process handling come from ``tests/lab/browser_support.py``
(the ``browser`` fixture): Debian's chromium, never Playwright's own download; without it
the test is skipped on a developer's machine and FAILS under ``CI=true``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from lab.demo.orchestrator import DEFAULT_MOTION
from tests.lab.browser_support import Browser, interrupt, page_up, start_cli
from tests.support import free_tcp_port, scaled, wait_until

pytestmark = pytest.mark.slow


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
    # the demo's own sweep at 20 mm/s instead of 45 (about 60 s instead of 25): the demo ends
    # with the sweep, and beside two CPU burners the page's first checks took longer than
    # 25 s, after which nothing moved on it any more
    motion = DEFAULT_MOTION.replace("speed=45", "speed=20")
    assert motion != DEFAULT_MOTION
    proc = start_cli(["demo", "--headless", "--workdir", str(tmp_path / "demo"), "--view",
                      f"127.0.0.1:{port}", "--motion", motion], log, stdout=log)
    url = f"http://127.0.0.1:{port}/"
    try:
        wait_until(lambda: page_up(url) or proc.poll() is not None, 90, "the demo's view")
        if proc.poll() is not None:
            pytest.fail(f"the demo ended early: {(tmp_path / 'demo.log').read_text()[-2000:]}")
        wait_until(lambda: _relay_url(tmp_path / "demo.log") is not None, 30,
                   "the relay's view URL printed")
        yield url, str(_relay_url(tmp_path / "demo.log"))
    finally:
        ended = interrupt(proc)  # Ctrl-C: the demo stops its children on the way out
        log.close()
    print(f"the demo exited {ended.seconds:.2f} s after SIGINT")
    assert not ended.killed, f"the demo ignored Ctrl-C for {ended.seconds:.0f} s"


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
                                            browser: Browser, tmp_path: Path) -> None:
    station_url, relay_url = demo_view
    errors = browser.errors
    artifacts = browser.artifacts
    page = browser.new_page("station page")
    page.goto(station_url)
    page.wait_for_function("() => window.teletouchView && teletouchView.messages > 5",
                           timeout=scaled(30) * 1e3)
    first = _view(page)
    pins0 = _canvas_signature(page, "pins")
    lat0 = _canvas_signature(page, "chart-latency")
    # pins change, the trajectory grows, the latency chart moves
    try:
        page.wait_for_function(
            f"""() => teletouchView.pinUpdates >= {first['pins'] + 10}
                   && teletouchView.trail.length >= {first['trail'] + 20}
                   && teletouchView.latencySamples >= {first['latency'] + 10}""",
            timeout=scaled(60) * 1e3)
    except Exception as err:  # say which one stood still
        logs = {name: (tmp_path / "demo" / f"{name}.log").read_text(errors="replace")[-1500:]
                for name in ("local", "remote") if (tmp_path / "demo" / f"{name}.log").exists()}
        pytest.fail(f"the view did not move: {first} -> {_view(page)} ({err}); demo log: "
                    f"{(tmp_path / 'demo.log').read_text(errors='replace')[-1500:]}; {logs}")
    wait_until(lambda: _canvas_signature(page, "pins") != pins0, 30, "the pins redrawn")
    wait_until(lambda: _canvas_signature(page, "chart-latency") != lat0, 30,
               "the latency chart moved")
    # the relay's page for observers: patch and trajectory from the routed messages
    observer = browser.new_page("relay page")
    observer.goto(relay_url)
    observer.wait_for_function(
        "() => teletouchView.messages > 5 && teletouchView.trail.length > 5"
        " && teletouchView.live && teletouchView.live.patch",
        timeout=scaled(30) * 1e3)
    observer_station = observer.evaluate("() => teletouchView.live.station")
    observer.screenshot(path=str(artifacts / "live_view_relay.png"), full_page=True,
                        timeout=scaled(60) * 1e3)
    # without the token the relay refuses the page's WebSocket
    refused = browser.browser.new_page()
    refused.goto(relay_url.split("#", 1)[0])
    refused.wait_for_function(
        "() => document.getElementById('conn').textContent.includes('refused')",
        timeout=scaled(30) * 1e3)
    observer.close()
    refused.close()
    # findings appear once the operator has palpated a tumor
    page.wait_for_selector("#findings li", timeout=scaled(150) * 1e3)
    seen = _view(page)
    time.sleep(0.5)  # let the page draw the finding before the picture is taken
    shot = artifacts / "live_view.png"
    page.screenshot(path=str(shot), full_page=True, timeout=scaled(60) * 1e3)
    print(f"live view screenshot: {shot}; state {seen}")
    badge = page.text_content("#link")
    assert seen["findings"] >= 1 and set(seen["kinds"]) <= {"benign", "malignant", "uncertain"}
    assert seen["trail"] > first["trail"] and seen["pins"] > first["pins"]
    assert badge is not None and "link" in badge
    assert shot.stat().st_size > 10_000
    assert observer_station == "relay"
    assert errors == [], f"page errors: {errors}"
