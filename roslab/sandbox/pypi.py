"""The sandbox upstream's STAND-IN Python package index (PEP 503 simple API), under /pypi/.

    /pypi/simple/<project>/   one page per project, linking its files with their sha256
    /pypi/files/<file>        the files: stand-in wheels, and stand-in sdists

Every file here is a STAND-IN named as one (its metadata's Summary, its module's docstring):
it carries the project's name, version and import name (`import RPi.GPIO`, `import smbus`),
nothing of the project's code. Projects that PyPI has only as sdists (RPi.GPIO, smbus) are
sdists here too, so the controller's fallback and the build on the host are exercised: their
build backend is in the sdist itself (PEP 517 `backend-path`), so building needs nothing from
the index and no compiler. Each stand-in wheel depends on one shared stand-in project, so a
requirement's dependency is downloaded as well.

Served for every `python_packages` entry of roslab's built-in profiles, and for
EXTRA_REQUIREMENTS: what the e2e tests' roster profiles name (the OSR rover's list from
the shared notes' field-facts.md, `../shared/notes` beside the clone). The requests land in
the upstream's request log, so a test counts how often each file was fetched.
"""

from __future__ import annotations

import base64
import hashlib
import io
import re
import tarfile
import textwrap
import zipfile
from pathlib import Path

STANDIN_NOTE = "roslab sandbox stand-in"
EXTRA_REQUIREMENTS = ("adafruit-circuitpython-servokit==1.3.17", "ina260==0.0.3", "RPi.GPIO==0.7.1",
                      "smbus==1.1.post2")
SDIST_ONLY = {"rpi-gpio", "smbus"}  # as on PyPI: no wheel at all
# The import name where it is not the project's name with - as _.
IMPORT_NAMES = {"adafruit-circuitpython-servokit": "adafruit_servokit", "rpi-gpio": "RPi.GPIO"}
COMMON = "roslab-sandbox-standin-common==1.0"  # every stand-in wheel's dependency


def normalized(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def builtin_requirements() -> list[str]:
    """Every python_packages entry of roslab's built-in profiles (both sides)."""
    from roslab.profiles.library import builtin_profiles

    found = []
    for profile in builtin_profiles().values():
        for side in profile.sides.values():
            found += [item for item in side.python_packages if item not in found]
    return found


def _module_files(project: str, version: str) -> dict[str, str]:
    """path -> text of the stand-in's importable module (packages made for dotted names)."""
    import_name = IMPORT_NAMES.get(normalized(project), normalized(project).replace("-", "_"))
    parts = import_name.split(".")
    text = (f'"""{STANDIN_NOTE} for {project} {version}: its name and version, none of its code."""\n'
            f"STANDIN = True\n__version__ = {version!r}\n")
    files = {f"{'/'.join(parts[:index])}/__init__.py": "" for index in range(1, len(parts))}
    files["/".join(parts) + ".py"] = text
    return files


def _metadata(project: str, version: str, requires: list[str]) -> str:
    lines = ["Metadata-Version: 2.1", f"Name: {project}", f"Version: {version}",
             f"Summary: {STANDIN_NOTE} for {project} (no code of the real project)",
             *(f"Requires-Dist: {item}" for item in requires)]
    return "\n".join(lines) + "\n"


def wheel_bytes(project: str, version: str, requires: list[str]) -> tuple[str, bytes]:
    """(file name, bytes) of a pure-Python stand-in wheel."""
    stem = f"{normalized(project).replace('-', '_')}-{version}"
    files = {path: text.encode() for path, text in _module_files(project, version).items()}
    files[f"{stem}.dist-info/METADATA"] = _metadata(project, version, requires).encode()
    files[f"{stem}.dist-info/WHEEL"] = (b"Wheel-Version: 1.0\nGenerator: roslab-sandbox\n"
                                        b"Root-Is-Purelib: true\nTag: py3-none-any\n")
    record = []
    for path, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{path},sha256={digest},{len(data)}")
    record.append(f"{stem}.dist-info/RECORD,,")
    files[f"{stem}.dist-info/RECORD"] = ("\n".join(record) + "\n").encode()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for path, data in files.items():
            info = zipfile.ZipInfo(path, date_time=(2020, 1, 1, 0, 0, 0))
            archive.writestr(info, data)
    return f"{stem}-py3-none-any.whl", out.getvalue()


# The sdists' own PEP 517 backend: writes the stand-in wheel from the files beside it.
BACKEND = textwrap.dedent('''\
    """{note}: a PEP 517 build backend that packs this sdist's module into a wheel."""
    import base64, hashlib, json, os, zipfile

    def _spec():
        with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "standin.json")) as handle:
            return json.load(handle)

    def get_requires_for_build_wheel(config_settings=None):
        return []

    def build_wheel(wheel_directory, config_settings=None, metadata_directory=None):
        spec = _spec()
        stem = spec["stem"]
        files = {{path: text.encode() for path, text in spec["files"].items()}}
        files[stem + ".dist-info/METADATA"] = spec["metadata"].encode()
        files[stem + ".dist-info/WHEEL"] = (b"Wheel-Version: 1.0\\nGenerator: roslab-sandbox\\n"
                                            b"Root-Is-Purelib: true\\nTag: py3-none-any\\n")
        record = []
        for path, data in files.items():
            digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
            record.append("%s,sha256=%s,%d" % (path, digest, len(data)))
        record.append(stem + ".dist-info/RECORD,,")
        files[stem + ".dist-info/RECORD"] = ("\\n".join(record) + "\\n").encode()
        name = stem + "-py3-none-any.whl"
        with zipfile.ZipFile(os.path.join(wheel_directory, name), "w") as archive:
            for path, data in files.items():
                archive.writestr(path, data)
        return name
    ''').format(note=STANDIN_NOTE)


def sdist_bytes(project: str, version: str) -> tuple[str, bytes]:
    """(file name, bytes) of a stand-in sdist that builds with its own backend."""
    import json

    root = f"{project}-{version}"
    stem = f"{normalized(project).replace('-', '_')}-{version}"
    spec = {"stem": stem, "files": _module_files(project, version), "metadata": _metadata(project, version, [])}
    files = {
        "PKG-INFO": _metadata(project, version, []),
        "pyproject.toml": ('[build-system]\nrequires = []\nbuild-backend = "standin_backend"\n'
                           'backend-path = ["."]\n'),
        "standin_backend.py": BACKEND,
        "standin.json": json.dumps(spec, indent=1) + "\n",
    }
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w:gz", format=tarfile.PAX_FORMAT) as archive:
        for path, text in files.items():
            data = text.encode()
            info = tarfile.TarInfo(f"{root}/{path}")
            info.size, info.mtime, info.mode = len(data), 1577836800, 0o644
            archive.addfile(info, io.BytesIO(data))
    return f"{root}.tar.gz", out.getvalue()


def build_index(serve_dir: Path, requirements: list[str] | None = None) -> dict[str, str]:
    """Write the stand-in index under `serve_dir`/pypi; returns file name -> project."""
    wanted = list(dict.fromkeys([*(requirements if requirements is not None else
                                   [*builtin_requirements(), *EXTRA_REQUIREMENTS]), COMMON]))
    root = Path(serve_dir) / "pypi"
    (root / "files").mkdir(parents=True, exist_ok=True)
    projects: dict[str, list[tuple[str, str]]] = {}
    served: dict[str, str] = {}
    for requirement in wanted:
        project, _, version = requirement.partition("==")
        if normalized(project) in SDIST_ONLY:
            name, data = sdist_bytes(project, version)
        else:
            requires = [] if requirement == COMMON else [COMMON]
            name, data = wheel_bytes(project, version, requires)
        (root / "files" / name).write_bytes(data)
        projects.setdefault(normalized(project), []).append((name, hashlib.sha256(data).hexdigest()))
        served[name] = project
    links = []
    for project, files in sorted(projects.items()):
        anchors = "".join(f'<a href="../../files/{name}#sha256={digest}">{name}</a>\n' for name, digest in files)
        page = root / "simple" / project / "index.html"
        page.parent.mkdir(parents=True, exist_ok=True)
        page.write_text(f"<!DOCTYPE html>\n<html><head><title>{STANDIN_NOTE}: {project}</title></head>"
                        f"<body>\n{anchors}</body></html>\n")
        links.append(f'<a href="{project}/">{project}</a>\n')
    (root / "simple" / "index.html").write_text(
        f"<!DOCTYPE html>\n<html><head><title>{STANDIN_NOTE} index</title></head><body>\n"
        + "".join(links) + "</body></html>\n")
    return served
