"""Architecture contracts: every ``[[tool.importlinter.contracts]]`` of pyproject.toml holds.

One test per contract id runs ``lint-imports`` from the venv on that contract, so a new
contract is tested by adding it to pyproject.toml (with an ``id``); nothing to add here.
``test_the_simulator_contract_catches_a_product_import`` proves the simulator contract is
not vacuous: the same contract, on the real import graph plus one product -> simulator
import, is broken.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _importlinter_config() -> dict[str, Any]:
    with PYPROJECT.open("rb") as fh:
        config: dict[str, Any] = tomllib.load(fh)["tool"]["importlinter"]
    return config


def _contract(contract_id: str) -> dict[str, Any]:
    return next(c for c in _importlinter_config()["contracts"] if c["id"] == contract_id)


CONTRACT_IDS = [c["id"] for c in _importlinter_config()["contracts"]]


@pytest.mark.parametrize("contract_id", CONTRACT_IDS)
def test_contract_is_kept(contract_id: str) -> None:
    if not LINT_IMPORTS.is_file():
        pytest.fail(f"{LINT_IMPORTS} missing: install the test extra (import-linter)")
    result = subprocess.run(
        [str(LINT_IMPORTS), "--config", str(PYPROJECT), "--contract", contract_id,
         "--no-cache"],
        cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_simulator_contract_catches_a_product_import() -> None:
    import grimp
    from importlinter.configuration import configure
    from importlinter.contracts.forbidden import ForbiddenContract

    configure()  # what the lint-imports entry point does first

    options = {k: v for k, v in _contract("product-without-simulators").items()
               if k not in ("id", "name", "type")}
    options = {k: [str(x) for x in v] if isinstance(v, list) else str(v)
               for k, v in options.items()}
    roots = _importlinter_config()["root_packages"]
    contract = ForbiddenContract(name="probe", session_options={"root_packages": roots},
                                 contract_options=options)
    assert contract.check(grimp.build_graph(*roots, cache_dir=None), verbose=False).kept
    graph = grimp.build_graph(*roots, cache_dir=None)  # check() edits the graph: a fresh one
    graph.add_import(importer="remote_site.tactile", imported="remote_site.phantom.phantom")
    assert not contract.check(graph, verbose=False).kept
