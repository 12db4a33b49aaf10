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

from pathlib import Path

import pytest

from shared.protocol import TactileFrame
from shared.recording import read_mcap
from tests.lab.browser_support import Browser, interrupt, page_up, start_cli
from tests.recordings import write_local_recording
from tests.support import free_tcp_port, scaled, wait_until

pytestmark = pytest.mark.slow

# every text the connection badge shows, from the page's first parse on (an init script)
_WATCH_BADGE = """window.connTexts = [];
new MutationObserver(() => {
  const el = document.getElementById('conn');
  if (el && connTexts[connTexts.length - 1] !== el.textContent) connTexts.push(el.textContent);
}).observe(document, {childList: true, characterData: true, subtree: true});"""


def test_a_replay_is_shown_in_the_live_view_and_labelled_as_a_replay(
        tmp_path: Path, browser: Browser) -> None:
    path = tmp_path / "session.mcap"
    write_local_recording(path, seconds=4.0)
    rec = read_mcap(path)
    last = [m.decode() for m in rec.on("/local/rx/tactile_frame")][-1]
    assert isinstance(last, TactileFrame)
    port = free_tcp_port()
    log = (tmp_path / "replay.log").open("wb")
    proc = start_cli(["replay", str(path), "--view", f"127.0.0.1:{port}", "--paused",
                      "--speed", "2", "--display", "none"], log)
    url = f"http://127.0.0.1:{port}/"
    try:
        wait_until(lambda: page_up(url) or proc.poll() is not None, 60, "the replay's view")
        assert proc.poll() is None, (tmp_path / "replay.log").read_text()[-2000:]
        page = browser.new_page("replay page")
        page.add_init_script(_WATCH_BADGE)
        page.goto(url)
        page.wait_for_function("() => teletouchView.messages > 3", timeout=scaled(30) * 1e3)
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
        page.wait_for_function("() => teletouchView.replay.paused", timeout=scaled(10) * 1e3)
        held = page.evaluate("() => [teletouchView.replay.position_us, teletouchView.messages]")
        page.wait_for_function(f"() => teletouchView.messages > {held[1] + 5}",
                               timeout=scaled(10) * 1e3)
        assert page.evaluate("() => teletouchView.replay.position_us") == held[0]
        assert "paused" in str(page.text_content("#conn"))
        page.click("#replay-toggle")
        page.wait_for_function("() => teletouchView.replay.ended", timeout=scaled(30) * 1e3)
        page.wait_for_function("() => teletouchView.messages > 0")
        seen = page.evaluate(
            """() => ({seq: teletouchView.live.patch.seq,
                       trail: teletouchView.trail.length,
                       position: document.getElementById('replay-position').textContent,
                       conn: connTexts, title: document.title})""")
        shot = browser.artifacts / "replay_view.png"
        page.screenshot(path=str(shot), full_page=True, timeout=scaled(60) * 1e3)
        print(f"replay view screenshot: {shot}; state {seen}")
        page.close()
    finally:
        ended = interrupt(proc)  # Ctrl-C: the way to end a replay's view
        log.close()
    print(f"the replay exited {ended.seconds:.2f} s after SIGINT"
          f"{' (KILLED: it did not exit)' if ended.killed else ''}")
    replay_log = (tmp_path / "replay.log").read_text()[-3000:]
    assert not ended.killed and proc.returncode == 0, replay_log
    assert seen["seq"] == last.seq  # the recording's last frame reached the page
    assert seen["trail"] > 10
    assert "(ended)" in seen["position"]
    # the connection badge never claimed a live session
    assert seen["conn"] and not any(t.strip() == "live" or t.startswith("live")
                                    for t in seen["conn"]), seen["conn"]
    assert any("REPLAY ended" in t for t in seen["conn"])
    assert b"replayed " in ended.stdout
    assert browser.errors == [], f"page errors: {browser.errors}"
