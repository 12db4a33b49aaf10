"""Fixtures of the lab tests: the headless browser of the live-view browser tests."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.lab.browser_support import Browser, headless_browser


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[Browser]:
    """Debian's chromium through Playwright (skips without it; fails under ``CI=true``)."""
    with headless_browser(tmp_path) as b:
        yield b
