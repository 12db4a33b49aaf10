"""The deploy image's dependency lock: every package `teletouch` runs on, pinned, with hashes.

``pyproject.toml`` gives lower bounds only (the project installs beside other software in a
lab's environment), so a plain ``pip install .`` takes whatever was released last: two
images built a month apart may run different numpy, OpenCV or websockets releases, and a
compromised or re-uploaded file would be taken as well. The image and the bare-metal units
install from ``deploy/requirements.lock`` instead, in pip's hash-checking mode: the same
releases every time, each file checked against its SHA-256.

What is locked: the runtime dependencies, the ``[cluster]`` extra (NATS) and the build
requirements (the image builds the project without build isolation, so nothing is fetched
unchecked), resolved by pip for CPython 3.11 on Linux, with the hashes of every file of each
release such an interpreter can install (manylinux wheels for x86_64 and aarch64, pure-Python
wheels and the source archive), taken from PyPI's index (its JSON simple API, PEP 691).

Usage (from the repository root)::

    python deploy/lock.py            # resolve again and rewrite deploy/requirements.lock
    python deploy/lock.py --check    # the lock still satisfies pyproject.toml (no network)

Regenerating needs network access to PyPI and the ``packaging`` module (it comes with
pytest); run it under Python 3.11 on Linux, the image's interpreter, so that pip resolves
the environment markers as the image will.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import subprocess
import sys
import tempfile
import tomllib
import urllib.request
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from packaging.markers import Marker, default_environment
from packaging.requirements import Requirement
from packaging.tags import Tag, compatible_tags, cpython_tags
from packaging.utils import (
    InvalidSdistFilename,
    InvalidWheelFilename,
    canonicalize_name,
    parse_sdist_filename,
    parse_wheel_filename,
)
from packaging.version import InvalidVersion, Version

ROOT = Path(__file__).resolve().parent.parent
LOCK = ROOT / "deploy" / "requirements.lock"
EXTRAS = ("cluster",)
INDEX = "https://pypi.org/simple"
#: the interpreter and platforms the lock serves (the image: python:3.11-slim, glibc)
PYTHON = (3, 11)
ARCHES = ("x86_64", "aarch64")


def _target_env(arch: str) -> dict[str, str]:
    """The target's environment markers on ``arch`` (the patch release is this
    interpreter's when it is a 3.11, as the image's is the latest 3.11)."""
    env = {key: str(value) for key, value in default_environment().items()}
    env.update(python_version="3.11", sys_platform="linux", platform_system="Linux",
               os_name="posix", implementation_name="cpython",
               platform_python_implementation="CPython", platform_machine=arch,
               python_full_version=platform.python_version()
               if sys.version_info[:2] == PYTHON else "3.11.0")
    return env


TARGET_ENVS = [_target_env(arch) for arch in ARCHES]
_PIN = re.compile(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9._+!-]+) \\")
_HASH = re.compile(r"--hash=sha256:([0-9a-f]{64})( \\)?")


class LockError(Exception):
    """The lock is malformed or no longer satisfies ``pyproject.toml``."""


@dataclass
class Pin:
    """One locked release: its version, the SHA-256 of its files, who needs it."""

    version: str
    hashes: list[str] = field(default_factory=list)
    via: list[str] = field(default_factory=list)


def wanted(pyproject: Path = ROOT / "pyproject.toml") -> list[Requirement]:
    """What the image needs: the runtime dependencies, ``EXTRAS`` and the build requirements,
    those whose markers hold on the target (``TARGET_ENV``)."""
    doc = tomllib.loads(pyproject.read_text())
    texts = list(doc["project"]["dependencies"])
    for extra in EXTRAS:
        texts += doc["project"]["optional-dependencies"][extra]
    texts += doc["build-system"]["requires"]
    return [r for r in map(Requirement, texts) if _holds(r.marker)]


def _holds(marker: Marker | None, extras: Iterable[str] = ("",)) -> bool:
    """``marker`` holds on the target, on some architecture and with one of ``extras``."""
    return marker is None or any(marker.evaluate({**env, "extra": extra})
                                 for env in TARGET_ENVS for extra in extras)


def parse_lock(text: str) -> dict[str, Pin]:
    """The pins of a lock file by canonical name.

    Read as pip reads it: a pin's hashes are the lines its backslashes join to it, so a hash
    after a line that does not end in one, or anything but a hash after one that does, is
    refused (pip would drop the hash, or join the next pin to this one and lose it).

    Raises:
        LockError: a line that is not a pin, a pin without a hash, a name twice.
    """
    pins: dict[str, Pin] = {}
    current: Pin | None = None
    joined = False  # the line before ended in a backslash: this one belongs to its pin
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if joined:
            found = _HASH.fullmatch(line)
            if current is None or found is None:
                raise LockError(f"line {number}: expected '--hash=sha256:<64 hex>' after the "
                                f"backslash above: {raw!r}")
            current.hashes.append(found.group(1))
            joined = found.group(2) is not None
            continue
        if not line or line.startswith("#"):
            if current is not None and line.startswith("#   "):
                current.via.append(line[4:].strip())
            continue
        found = _PIN.fullmatch(line)
        if found is None or raw[0].isspace():
            raise LockError(f"line {number}: expected 'name==version \\': {raw!r}")
        joined = True
        key = canonicalize_name(found.group(1))
        if key in pins:
            raise LockError(f"line {number}: {key} is pinned twice")
        current = pins[key] = Pin(found.group(2))
    if joined:
        raise LockError("the last line ends in a backslash")
    for name, pin in pins.items():
        if not pin.hashes:
            raise LockError(f"{name}=={pin.version} has no hash")
    return pins


def check(pins: dict[str, Pin], reqs: Iterable[Requirement]) -> None:
    """Every requirement is pinned to a release it allows.

    Raises:
        LockError: naming each requirement missing from the lock or pinned outside its range.
    """
    problems = []
    for req in reqs:
        pin = pins.get(canonicalize_name(req.name))
        if pin is None:
            problems.append(f"{req} is not in the lock")
        elif not req.specifier.contains(  # a pre-release only where one is named
                pin.version, prereleases=bool(req.specifier.prereleases)):
            problems.append(f"{req} but the lock pins {pin.version}")
    if problems:
        raise LockError("; ".join(problems) + " (regenerate: python deploy/lock.py)")


def target_tags() -> dict[str, set[Tag]]:
    """The wheel tags CPython 3.11 on glibc Linux installs, per architecture (any manylinux
    glibc version: the image's glibc is newer than every wheel's floor)."""
    tags = {}
    for arch in ARCHES:
        platforms = [f"manylinux_2_{minor}_{arch}" for minor in range(5, 60)]
        platforms += [f"manylinux2014_{arch}", f"linux_{arch}"]
        if arch == "x86_64":
            platforms += ["manylinux2010_x86_64", "manylinux1_x86_64"]
        tags[arch] = set(cpython_tags(PYTHON, platforms=platforms)) | \
            set(compatible_tags(PYTHON, "cp311", platforms=platforms))
    return tags


def select_files(files: list[dict[str, Any]], version: str,
                 tags: dict[str, set[Tag]]) -> list[str]:
    """The SHA-256 of the files of ``version`` the target installs, from an index's JSON
    simple API answer (PEP 691 ``files``): wheels with a tag of an architecture in ``tags``
    and the source archive; never a yanked file.

    Raises:
        LockError: an architecture without a wheel (it would build from source, which the
            slim image cannot for a compiled package: an explicit decision, not a default).
    """
    wanted_version = Version(version)
    hashes = set()
    wheels_for = set()
    for item in files:
        filename = item["filename"]
        if item.get("yanked") or "sha256" not in item.get("hashes", {}):
            continue
        try:
            if filename.endswith(".whl"):
                _, found, _, file_tags = parse_wheel_filename(filename)
                arches = {arch for arch, usable in tags.items() if file_tags & usable}
                if found == wanted_version and arches:
                    hashes.add(item["hashes"]["sha256"])
                    wheels_for |= arches
            elif parse_sdist_filename(filename)[1] == wanted_version:  # the source archive
                hashes.add(item["hashes"]["sha256"])
        except (InvalidWheelFilename, InvalidSdistFilename, InvalidVersion):
            continue  # an old file named otherwise: never this release's
    missing = sorted(set(tags) - wheels_for)
    if missing:
        raise LockError(f"=={version}: no wheel for CPython 3.11 on Linux {', '.join(missing)}")
    return sorted(hashes)


def _release_files(name: str, version: str, tags: dict[str, set[Tag]]) -> list[str]:
    request = urllib.request.Request(f"{INDEX}/{name}/",
                                      headers={"Accept": "application/vnd.pypi.simple.v1+json"})
    with urllib.request.urlopen(request, timeout=60) as answer:
        files = json.load(answer)["files"]
    try:
        return select_files(files, version, tags)
    except LockError as err:
        raise LockError(f"{name}{err} at {INDEX}") from None


def resolve(root: Path = ROOT) -> dict[str, Pin]:
    """Resolve the project's needs with pip from PyPI (``pip --isolated``: no local index,
    constraint or find-links setting of this host takes part).

    Raises:
        LockError: not run under CPython 3.11 on Linux (pip resolves for the interpreter it
            runs under, so the lock would not be the image's).
    """
    if sys.version_info[:2] != PYTHON or sys.platform != "linux" or \
            sys.implementation.name != "cpython":
        raise LockError(f"run under CPython {PYTHON[0]}.{PYTHON[1]} on Linux, the image's "
                        f"interpreter (this is {platform.python_implementation()} "
                        f"{platform.python_version()} on {sys.platform})")
    doc = tomllib.loads((root / "pyproject.toml").read_text())
    project = canonicalize_name(doc["project"]["name"])
    build = {canonicalize_name(Requirement(t).name): t for t in doc["build-system"]["requires"]}
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        subprocess.run([sys.executable, "-m", "pip", "--isolated", "install", "--dry-run",
                        "--ignore-installed", "--quiet", "--report", str(report),
                        f"{root}[{','.join(EXTRAS)}]", *build.values()], check=True)
        installs = json.loads(report.read_text())["install"]
    pins: dict[str, Pin] = {canonicalize_name(i["metadata"]["name"]):
                            Pin(i["metadata"]["version"]) for i in installs}
    needs = {canonicalize_name(i["metadata"]["name"]):
             [Requirement(t) for t in i["metadata"].get("requires_dist", [])] for i in installs}
    asked: dict[str, set[str]] = {project: set(EXTRAS)}  # the extras anyone asks of a package
    for reqs in needs.values():
        for req in reqs:
            asked.setdefault(canonicalize_name(req.name), set()).update(req.extras)
    for parent, reqs in needs.items():  # who needs what, by the requirements that hold
        for req in reqs:
            child = canonicalize_name(req.name)
            if child in pins and child != parent and \
                    _holds(req.marker, ("", *asked.get(parent, ()))):
                pins[child].via.append(parent)
    pins.pop(project)
    tags = target_tags()
    for name, pin in pins.items():
        pin.via = sorted(set(pin.via)) or (["build"] if name in build else [])
        pin.hashes = _release_files(name, pin.version, tags)
    return pins


def render(pins: dict[str, Pin]) -> str:
    """The lock file's text: pins sorted by name, each with its hashes and who needs it."""
    lines = ["# Generated by `python deploy/lock.py` from pyproject.toml (runtime, [cluster] and",
             "# build requirements) for CPython 3.11 on Linux. Do not edit: regenerate.",
             "# Install: pip install --require-hashes --no-deps -r deploy/requirements.lock", ""]
    for name in sorted(pins):
        pin = pins[name]
        lines.append(f"{name}=={pin.version} \\")
        lines += [f"    --hash=sha256:{h}" + (" \\" if i < len(pin.hashes) - 1 else "")
                  for i, h in enumerate(pin.hashes)]
        lines.append("    # via")
        lines += [f"    #   {v}" for v in pin.via]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="only check the lock against pyproject.toml (no network)")
    args = parser.parse_args(argv)
    try:
        if args.check:
            check(parse_lock(LOCK.read_text()), wanted())
            print(f"{LOCK.relative_to(ROOT)} satisfies pyproject.toml")
            return 0
        pins = resolve()
        check(pins, wanted())
        LOCK.write_text(render(pins))
    except LockError as err:
        print(f"lock: {err}", file=sys.stderr)
        return 1
    print(f"wrote {LOCK.relative_to(ROOT)}: {len(pins)} releases, "
          f"{sum(len(p.hashes) for p in pins.values())} files")
    return 0


if __name__ == "__main__":
    sys.exit(main())
