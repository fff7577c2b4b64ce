"""A robot profile's Python requirements, downloaded once per class into the controller's wheelhouse.

The machine running pyinfra runs `pip download` (its own Python's pip, never a Pi's) for each
*target* the class's hosts are: the machine (`uname -m`), glibc and Python (major.minor) the
host reported (deploy/python_env.py reads them in the probe), never assumed from a board or
a release. The files land in

    <python_wheelhouse_dir>/<target>/<digest of the index URL and the requirements>/

with a manifest (`roslab-wheelhouse.json`: each file, its sha256, wheel or sdist) written
last, when everything is there; a folder with a manifest is complete and is never downloaded
again: every requirement is pinned `name==version`, so its files do not change upstream.
A host then gets these files and installs from them alone (`pip install --no-index`).

What holds, per requirement (in the order given):

1. A wheel for the target with its dependencies (`pip download --only-binary=:all:` with
   `--platform manylinux_<glibc>_<machine>` (pip adds the older manylinux tags),
   `--platform linux_<machine>` (indexes like piwheels), `--implementation cp` and
   `--python-version`): a pure-Python wheel, or one built for the target.
2. Where the index has no wheel for the target (RPi.GPIO, smbus on PyPI: sdists only), the
   requirement's sdist (`--no-binary=:all: --no-deps`), built on the host by pip from the
   pushed file: the host needs a compiler and the Python headers (`python_sdist_build_packages`,
   installed only when the wheelhouse holds an sdist) and the sdist's build backend, which is
   downloaded here too (its pyproject.toml's `build-system.requires`, or pip's default
   `setuptools>=40.8.0` and `wheel` without one). An sdist's own dependencies are not followed
   (they are only known once it is built): list them in python_packages as well.

Each (target, requirement set) is downloaded at most once per run (hosts are planned one after
another, possibly in threads), and a failure is remembered, naming the requirement and pip's
reason, for the deploy to stop only the hosts that need it. `offline`: only the wheelhouse.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import threading
import urllib.parse
import zipfile
from dataclasses import dataclass
from pathlib import Path

MANIFEST = "roslab-wheelhouse.json"
TIMEOUT = 900  # seconds for one pip download (a requirement with its dependencies)
# pip's build requirements for an sdist without pyproject.toml (PEP 517's fallback).
DEFAULT_BUILD_REQUIRES = ("setuptools>=40.8.0", "wheel")
# What a file in a wheelhouse may be called: it becomes a file name on every host and a word
# in a shell command (quoted all the same).
_FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,200}\.(whl|tar\.gz|zip)", re.ASCII)
_MACHINE = re.compile(r"[a-z0-9_]{1,32}", re.ASCII)
_VERSION = re.compile(r"[0-9]{1,3}\.[0-9]{1,3}", re.ASCII)
# A build requirement an sdist names: a requirement specifier, never an option for pip.
_BUILD_REQUIREMENT = re.compile(r"[A-Za-z0-9][A-Za-z0-9._\-\[\], <>=!~;'\"()]*", re.ASCII)


_OTHER_SOURCES = ("PIP_INDEX_URL", "PIP_EXTRA_INDEX_URL", "PIP_FIND_LINKS", "PIP_NO_INDEX", "PIP_PLATFORM",
                  "PIP_PYTHON_VERSION", "PIP_ONLY_BINARY", "PIP_NO_BINARY", "PIP_REQUIREMENT",
                  "PIP_CONSTRAINT", "PIP_PRE")


class WheelhouseError(Exception):
    """A requirement the controller could not download, or an offline wheelhouse missing it."""


@dataclass(frozen=True)
class Target:
    """What a host runs Python on: its machine, glibc and Python (major.minor)."""

    machine: str  # uname -m: aarch64, x86_64, armv7l
    glibc: str  # 2.39
    python: str  # 3.12

    def problem(self) -> str | None:
        if not _MACHINE.fullmatch(self.machine):
            return f"the host's machine type {self.machine!r} is not one pip knows"
        if not _VERSION.fullmatch(self.glibc):
            return f"the host's C library is not glibc (found {self.glibc!r}): no wheel can be chosen for it"
        if not _VERSION.fullmatch(self.python):
            return f"the host has no python3 (found {self.python!r})"
        return None

    @property
    def name(self) -> str:
        return f"cp{self.python.replace('.', '')}-{self.machine}-glibc{self.glibc}"

    def describe(self) -> str:
        return f"Python {self.python} on {self.machine} (glibc {self.glibc})"

    def pip_options(self) -> list[str]:
        glibc = self.glibc.replace(".", "_")
        return ["--only-binary=:all:", "--platform", f"manylinux_{glibc}_{self.machine}",
                "--platform", f"linux_{self.machine}", "--implementation", "cp",
                "--python-version", self.python]


@dataclass(frozen=True)
class File:
    name: str
    sha256: str
    sdist: bool


@dataclass(frozen=True)
class Wheelhouse:
    """A complete wheelhouse for one target and requirement set, on the controller."""

    path: Path
    requirements: tuple[str, ...]
    files: tuple[File, ...]

    @property
    def has_sdist(self) -> bool:
        return any(item.sdist for item in self.files)

    def read(self, name: str) -> bytes:
        return (self.path / name).read_bytes()

    @property
    def requirements_text(self) -> str:
        return "".join(f"{item}\n" for item in self.requirements)

    @property
    def digest(self) -> str:
        """Names this requirement set and its files: the hosts' install stamp."""
        text = self.requirements_text + "".join(f"{item.name} {item.sha256}\n" for item in self.files)
        return hashlib.sha256(text.encode()).hexdigest()


def _set_key(requirements: list[str], index_url: str) -> str:
    return hashlib.sha256("\n".join([index_url, *sorted(requirements)]).encode()).hexdigest()[:16]


def set_dir(cache_dir: str | Path, target: Target, requirements: list[str], index_url: str) -> Path:
    return Path(cache_dir).expanduser() / target.name / _set_key(requirements, index_url)


def kept_for_any_target(requirements: list[str], index_url: str, cache_dir: str | Path) -> list[Wheelhouse]:
    """The complete wheelhouses of `requirements` kept for any target (their manifests only)."""
    found: list[Wheelhouse] = []
    if not cache_dir or not index_url:
        return found
    key = _set_key(requirements, index_url)
    try:
        targets = sorted(Path(cache_dir).expanduser().iterdir())
    except OSError:
        return found
    for target_dir in targets:
        kept = load(target_dir / key, check_files=False)
        if kept is not None:
            found.append(kept)
    return found


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _is_sdist(name: str) -> bool:
    return not name.endswith(".whl")


def load(path: Path, check_files: bool = True) -> Wheelhouse | None:
    """The complete wheelhouse at `path` (its manifest and, with `check_files`, each file's
    sha256 checked), or None."""
    try:
        manifest = json.loads((path / MANIFEST).read_text())
        files = tuple(File(item["name"], item["sha256"], bool(item["sdist"])) for item in manifest["files"])
        requirements = tuple(str(item) for item in manifest["requirements"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    for item in files:
        if not _FILE_NAME.fullmatch(item.name):
            return None
        if not check_files:
            continue
        try:
            if _sha256(path / item.name) != item.sha256:
                return None
        except OSError:
            return None
    return Wheelhouse(path, requirements, files)


def pip_download_command(target: Target, index_url: str, dest: Path, requirements: list[str],
                         sdist: bool = False) -> list[str]:
    """The controller's `pip download` of `requirements` for `target` (argv, no shell)."""
    command = [sys.executable, "-m", "pip", "download", "--dest", str(dest), "--index-url", index_url,
               "--no-cache-dir", "--disable-pip-version-check", "--no-input", "--progress-bar", "off",
               "--timeout", "60", "--retries", "2"]
    parts = urllib.parse.urlsplit(index_url)
    if parts.scheme == "http" and parts.hostname:
        # pip ignores a plain-http index unless told: the roster's http:// URL (a classroom
        # mirror, the sandbox's upstream) is the teacher's choice, so it is trusted as written.
        command += ["--trusted-host", parts.netloc.rpartition("@")[2]]
    if sdist:
        command += ["--no-binary=:all:", "--no-deps"]
    else:
        command += target.pip_options()
    # Every requirement starts with a letter or digit (checked), so none is read as an option.
    return [*command, *requirements]


def _pip_reason(output: str) -> str:
    """pip's own reason, in one line (its first ERROR line, else its last line)."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    for line in lines:
        if line.startswith("ERROR:"):
            return line[len("ERROR:"):].strip()
    return lines[-1] if lines else "pip gave no reason"


def _run_pip(command: list[str]) -> tuple[bool, str]:
    # Only the roster's index: no pip.conf, and none of the controller's PIP_* variables that add
    # other places to download from (its certificate and proxy settings stay).
    env = {name: value for name, value in os.environ.items() if name not in _OTHER_SOURCES}
    env["PIP_CONFIG_FILE"] = os.devnull
    try:
        done = subprocess.run(command, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                              timeout=TIMEOUT, env=env)
    except subprocess.TimeoutExpired:
        return False, f"pip did not finish within {TIMEOUT} s"
    except OSError as error:
        return False, f"cannot run pip: {error}"
    return done.returncode == 0, done.stdout + done.stderr


def build_requires(sdist: Path) -> list[str]:
    """What building `sdist` needs (its pyproject.toml's build-system.requires, or pip's default)."""
    text = None
    try:
        if sdist.name.endswith(".zip"):
            with zipfile.ZipFile(sdist) as archive:
                names = [n for n in archive.namelist() if n.count("/") == 1 and n.endswith("/pyproject.toml")]
                text = archive.read(names[0]).decode() if names else None
        else:
            with tarfile.open(sdist, "r:gz") as archive:
                members = [m for m in archive.getmembers()
                           if m.isfile() and m.name.count("/") == 1 and m.name.endswith("/pyproject.toml")]
                member = archive.extractfile(members[0]) if members else None  # None: not a file
                if member is not None:
                    text = member.read().decode()
    except (OSError, tarfile.TarError, zipfile.BadZipFile, UnicodeDecodeError, KeyError):
        raise WheelhouseError(f"{sdist.name} is not a readable sdist") from None
    if text is None:
        return list(DEFAULT_BUILD_REQUIRES)
    system = _build_system(text, sdist.name)
    if not isinstance(system, dict) or "requires" not in system:
        return list(DEFAULT_BUILD_REQUIRES)
    requires = system["requires"]
    if not isinstance(requires, list) or not all(
            isinstance(item, str) and _BUILD_REQUIREMENT.fullmatch(item) for item in requires):
        raise WheelhouseError(f"{sdist.name}: build-system.requires is not a list of requirements")
    return list(requires)


def _build_system(text: str, name: str):
    """pyproject.toml's [build-system] table (tomllib; Python 3.10's pip's own tomli)."""
    if sys.version_info >= (3, 11):
        import tomllib as toml
    else:  # Python 3.10
        from pip._vendor import tomli as toml
    try:
        return toml.loads(text).get("build-system")
    except toml.TOMLDecodeError:
        raise WheelhouseError(f"{name}: its pyproject.toml is not TOML") from None


def _download(path: Path, target: Target, requirements: list[str], index_url: str) -> Wheelhouse:
    path.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    try:
        sdists: list[str] = []
        for requirement in requirements:
            ok, output = _run_pip(pip_download_command(target, index_url, work, [requirement]))
            if ok:
                continue
            wheel_reason = _pip_reason(output)
            before = set(os.listdir(work))
            ok, output = _run_pip(pip_download_command(target, index_url, work, [requirement], sdist=True))
            if not ok:
                raise WheelhouseError(f"pip could not download {requirement} for {target.describe()} from "
                                      f"{index_url}: {wheel_reason}")
            sdists += [name for name in os.listdir(work) if name not in before]
        for name in sdists:
            requires = build_requires(work / name)
            if requires:
                ok, output = _run_pip(pip_download_command(target, index_url, work, requires))
                if not ok:
                    raise WheelhouseError(f"pip could not download {', '.join(requires)} (to build {name}) "
                                          f"for {target.describe()} from {index_url}: {_pip_reason(output)}")
        files = []
        for name in sorted(os.listdir(work)):
            if not _FILE_NAME.fullmatch(name) or not (work / name).is_file():
                raise WheelhouseError(f"pip downloaded {name!r}, which is not a wheel or an sdist roslab "
                                      "can copy to the hosts")
            files.append(File(name, _sha256(work / name), _is_sdist(name)))
        manifest = {"target": target.name, "index_url": index_url, "requirements": list(requirements),
                    "files": [{"name": f.name, "sha256": f.sha256, "sdist": f.sdist} for f in files]}
        (work / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        shutil.rmtree(path, ignore_errors=True)  # an incomplete folder (no manifest) from before
        os.replace(work, path)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return Wheelhouse(path, tuple(requirements), tuple(files))


_lock = threading.Lock()
_this_run: dict[tuple, Wheelhouse | WheelhouseError] = {}


def wheelhouse(requirements: list[str], target: Target, index_url: str, cache_dir: str | Path,
               offline: bool = False) -> Wheelhouse:
    """The complete wheelhouse for `requirements` on `target`: kept, else downloaded once.

    WheelhouseError (remembered for the run) names the requirement and the reason.
    """
    problem = target.problem()
    if problem:
        raise WheelhouseError(problem)
    path = set_dir(cache_dir, target, requirements, index_url)
    key = (str(path), offline)
    with _lock:
        known = _this_run.get(key)
        if known is None:
            try:
                known = load(path)
                if known is None and offline:
                    raise WheelhouseError(
                        f"offline, and the controller's wheelhouse has no complete download of "
                        f"{', '.join(requirements)} for {target.describe()} ({path}): run once online first")
                if known is None:
                    known = _download(path, target, list(requirements), index_url)
            except WheelhouseError as error:
                known = error
            except OSError as error:
                known = WheelhouseError(f"cannot write the wheelhouse {path}: {error.strerror or error}")
            _this_run[key] = known
    if isinstance(known, WheelhouseError):
        raise known
    return known
