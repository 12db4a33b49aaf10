"""A replay in the live view, in a real headless browser (Playwright + Debian's chromium).

``teletouch replay FILE --view HOST:PORT --paused`` runs as a process; chromium opens the
page, and the test checks what a person would see: the page says REPLAY (title, banner,
connection badge) from the first snapshot on and never "live"; play starts it, the replayed
frames, pins and trajectory reach the page up to the recording's last frame; pause holds the
position; the end is shown as such. A screenshot is kept (``$TELETOUCH_TEST_ARTIFACTS`` or
pytest's tmp dir). Like the live view's browser test it skips without chromium or
playwright on a developer's machine and FAILS under ``CI=true``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from shared.protocol import TactileFrame
from shared.recording import read_mcap
from tests.lab.test_view_browser import _chromium, _page_up, _playwright
from tests.recordings import write_local_recording
from tests.support import REPO_ROOT, free_tcp_port, scaled, wait_until

pytestmark = pytest.mark.slow

# every text the connection badge shows, from the page's first parse on (an init script)
_WATCH_BADGE = """window.connTexts = [];
new MutationObserver(() => {
  const el = document.getElementById('conn');
  if (el && connTexts[connTexts.length - 1] !== el.textContent) connTexts.push(el.textContent);
}).observe(document, {childList: true, characterData: true, subtree: true});"""


def test_a_replay_is_shown_in_the_live_view_and_labelled_as_a_replay(tmp_path: Path) -> None:
    chromium = _chromium()
    sync_playwright = _playwright()
    path = tmp_path / "session.mcap"
    write_local_recording(path, seconds=4.0)
    rec = read_mcap(path)
    last = [m.decode() for m in rec.on("/local/rx/tactile_frame")][-1]
    assert isinstance(last, TactileFrame)
    port = free_tcp_port()
    log = (tmp_path / "replay.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "lab.cli", "replay", str(path), "--view", f"127.0.0.1:{port}",
         "--paused", "--speed", "2", "--display", "none"],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=log,
        start_new_session=True)  # its analysis child too can be killed as a group
    url = f"http://127.0.0.1:{port}/"
    artifacts = Path(os.environ.get("TELETOUCH_TEST_ARTIFACTS") or tmp_path)
    artifacts.mkdir(parents=True, exist_ok=True)
    errors: list[str] = []
    try:
        wait_until(lambda: _page_up(url) or proc.poll() is not None, 60, "the replay's view")
        assert proc.poll() is None, (tmp_path / "replay.log").read_text()[-2000:]
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, headless=True,
                                         args=["--no-sandbox", "--disable-gpu"])
            try:
                page = browser.new_page(viewport={"width": 1600, "height": 900})
                page.on("pageerror", lambda err: errors.append(str(err)))
                page.add_init_script(_WATCH_BADGE)
                page.goto(url)
                page.wait_for_function("() => teletouchView.messages > 3",
                                       timeout=scaled(30) * 1e3)
                paused = page.evaluate("() => teletouchView.replay")
                assert paused["paused"] and paused["position_s"] == 0
                assert page.is_visible("#replay-bar")
                assert "REPLAY" in page.title() and "not live" in page.title()
                assert "REPLAY" in str(page.text_content("#conn"))
                # play: frames, pins and the trajectory arrive
                page.click("#replay-toggle")
                page.wait_for_function(
                    """() => teletouchView.live.patch && teletouchView.live.patch.seq > 10
                         && teletouchView.trail.length > 10 && teletouchView.pinUpdates > 5""",
                    timeout=scaled(30) * 1e3)
                # pause: the position holds while snapshots keep coming
                page.click("#replay-toggle")
                page.wait_for_function("() => teletouchView.replay.paused",
                                       timeout=scaled(10) * 1e3)
                held = page.evaluate("() => [teletouchView.replay.position_us,"
                                     " teletouchView.messages]")
                page.wait_for_function(f"() => teletouchView.messages > {held[1] + 5}",
                                       timeout=scaled(10) * 1e3)
                assert page.evaluate("() => teletouchView.replay.position_us") == held[0]
                assert "paused" in str(page.text_content("#conn"))
                page.click("#replay-toggle")
                page.wait_for_function("() => teletouchView.replay.ended",
                                       timeout=scaled(30) * 1e3)
                page.wait_for_function("() => teletouchView.messages > 0")
                seen = page.evaluate(
                    """() => ({seq: teletouchView.live.patch.seq,
                               trail: teletouchView.trail.length,
                               position: document.getElementById('replay-position').textContent,
                               conn: connTexts, title: document.title})""")
                shot = artifacts / "replay_view.png"
                page.screenshot(path=str(shot), full_page=True, timeout=scaled(60) * 1e3)
                print(f"replay view screenshot: {shot}; state {seen}")
            finally:
                with contextlib.suppress(Exception):
                    browser.close()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # the way to end a replay's view
        try:
            out, _ = proc.communicate(timeout=scaled(30))
        except subprocess.TimeoutExpired:
            # a child holding stdout would make an unbounded communicate() hang: kill the
            # whole group and read what is there
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            out, _ = proc.communicate(timeout=scaled(10))
        log.close()
    assert seen["seq"] == last.seq  # the recording's last frame reached the page
    assert seen["trail"] > 10
    assert "(ended)" in seen["position"]
    # the connection badge never claimed a live session
    assert seen["conn"] and not any(t.strip() == "live" or t.startswith("live")
                                    for t in seen["conn"]), seen["conn"]
    assert any("REPLAY ended" in t for t in seen["conn"])
    assert proc.returncode == 0, (tmp_path / "replay.log").read_text()[-2000:]
    assert b"replayed " in out
    assert errors == [], f"page errors: {errors}"
