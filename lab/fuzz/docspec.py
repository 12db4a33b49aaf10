"""The error table of ``docs/protocol.md`` §6, parsed from the doc at run time.

The fuzz oracles take every error code, close code and fatality from here, not from the code
under test: an answer the relay gives that the doc does not describe is a finding, and so is
a doc row that the code contradicts.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

__all__ = ["DOC_PATH", "ErrorRule", "Fatality", "error_table"]

#: the specification (``lab/fuzz/docspec.py`` -> ``<repo>/docs/protocol.md``)
DOC_PATH = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"

_ROW = re.compile(r"^\|\s*`(?P<code>[a-z_]+)`\s*\|\s*(?P<close>[^|]*)\|\s*(?P<fatal>[^|]*)\|")


class Fatality(Enum):
    """When an error of a code ends the connection, as the doc's "fatal?" column says."""

    ALWAYS = "always"
    BEFORE_HELLO = "before hello"  # fatal before the hello, per message after it
    PER_MESSAGE = "per message"


@dataclass(frozen=True)
class ErrorRule:
    """One row of the table: code, WebSocket close code (None: no close), fatality, and
    whether the error counts toward ``too_many_errors``."""

    code: str
    close_code: int | None
    fatality: Fatality
    counted: bool


@functools.cache
def error_table(path: Path = DOC_PATH) -> dict[str, ErrorRule]:
    """Parse the §6 table (code -> rule).

    Raises:
        ValueError: the section or a row cannot be read (the doc changed shape).
    """
    text = path.read_text(encoding="utf-8")
    start = text.find("## 6. Errors and close codes")
    if start < 0:
        raise ValueError(f"{path}: no section '## 6. Errors and close codes'")
    rules: dict[str, ErrorRule] = {}
    for line in text[start:].splitlines():
        m = _ROW.match(line)
        if m is None:
            continue
        close_s, fatal_s = m["close"].strip(), m["fatal"].strip().lower()
        close = re.match(r"\d+", close_s)
        if fatal_s.startswith("yes"):
            fatality = Fatality.ALWAYS
        elif "before hello" in fatal_s:
            fatality = Fatality.BEFORE_HELLO
        elif fatal_s.startswith("per message"):
            fatality = Fatality.PER_MESSAGE
        else:
            raise ValueError(f"{path}: cannot read the fatal? column of {m['code']!r}: "
                             f"{fatal_s!r}")
        rules[m["code"]] = ErrorRule(m["code"], int(close.group()) if close else None,
                                     fatality, "not counted" not in fatal_s)
    if not rules:
        raise ValueError(f"{path}: §6 has no error rows")
    return rules
