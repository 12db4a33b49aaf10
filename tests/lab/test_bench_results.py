"""Where benchmark results go: one helper writes the committed files for every benchmark."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from lab.bench.results import publish, write_results


def test_write_results_writes_markdown_strict_json_and_the_plot(tmp_path: Path) -> None:
    drawn: list[Path] = []
    out = write_results(tmp_path / "new" / "dir", "thing", "# table\n\n| a |\n\n\n",
                        data={"p99": math.nan, "rows": (1, 2)}, plot=drawn.append)
    assert out == tmp_path / "new" / "dir"
    assert (out / "thing.md").read_text() == "# table\n\n| a |\n"  # one final newline
    assert json.loads((out / "thing.json").read_text()) == {"p99": None, "rows": [1, 2]}
    assert drawn == [out / "thing.png"]


def test_write_results_without_data_writes_no_json(tmp_path: Path) -> None:
    write_results(tmp_path, "fuzz", "text")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fuzz.md"]


@pytest.mark.parametrize("as_json", [True, False])
def test_publish_prints_one_form_and_writes_both(tmp_path: Path, as_json: bool,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    publish({"sessions_held": 3}, "| sessions | 3 |", as_json=as_json, out_dir=tmp_path,
            stem="load")
    printed = capsys.readouterr().out
    if as_json:
        assert json.loads(printed) == {"sessions_held": 3}
    else:
        assert printed == "| sessions | 3 |\n"
    assert (tmp_path / "load.md").read_text() == "| sessions | 3 |\n"
    assert json.loads((tmp_path / "load.json").read_text()) == {"sessions_held": 3}


def test_publish_without_out_dir_writes_nothing(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    publish({"a": 1}, "md", as_json=False, out_dir=None, stem="x")
    assert capsys.readouterr().out == "md\n"
    assert list(tmp_path.iterdir()) == []
