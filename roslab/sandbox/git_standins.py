"""Stand-in git repositories the sandbox upstream serves under /git/ (roslab sandbox stand-in).

The internet's git hosts are out of reach here: the upstream serves bare repositories with
git's dumb HTTP protocol (static files: `info/refs` and the objects, kept current by
`git update-server-info`) from its served tree, so every fetch appears in its request log.
A repository named by a .repos file (`https://github.com/owner/name.git`) is served at
`<upstream>/git/github.com/owner/name.git`, and the sandbox roster's `source_url_rewrites`
points `https://github.com/` there, as a classroom would point it at a local git server.

Each stand-in holds one ament_python package (named from the repository's path, or as
given) with a console script that prints what it is and exits: no real robot code. Its
README says it is a stand-in. A tag the .repos file pins is made on its commit; a pinned
commit cannot be made (its hash is the real history's): such a stand-in carries the tag
STANDIN_TAG, and the sandbox roster's `source_pins` (a setting a teacher has too) builds it.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path
from urllib.parse import urlsplit

STANDIN_NOTE = "roslab sandbox stand-in"
GIT_ROOT = "git"
_GIT_ENV = {
    "GIT_CONFIG_NOSYSTEM": "1", "GIT_CONFIG_GLOBAL": os.devnull, "LC_ALL": "C",
    "GIT_AUTHOR_NAME": "roslab sandbox", "GIT_AUTHOR_EMAIL": "sandbox@roslab.invalid",
    "GIT_COMMITTER_NAME": "roslab sandbox", "GIT_COMMITTER_EMAIL": "sandbox@roslab.invalid",
    # fixed dates: the same stand-in is the same commit on every machine and every `up`
    "GIT_AUTHOR_DATE": "2026-01-01T00:00:00Z", "GIT_COMMITTER_DATE": "2026-01-01T00:00:00Z",
}


def _git(*args, cwd: Path | None = None, env: dict | None = None) -> str:
    done = subprocess.run(["git", *map(str, args)], cwd=cwd, env={**os.environ, **_GIT_ENV, **(env or {})},
                          capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if done.returncode:
        raise RuntimeError(f"git {' '.join(map(str, args))}: {done.stderr.strip()}")
    return done.stdout.strip()


def served_path(url: str) -> str:
    """Where a repository URL is served, relative to the served tree: git/<host>/<path>."""
    parts = urlsplit(url)
    path = parts.path.strip("/")
    if not path.endswith(".git"):
        path += ".git"
    return f"{GIT_ROOT}/{parts.hostname}/{path}"


def package_name(repo_path: str) -> str:
    name = re.sub(r"[^a-z0-9_]", "_", repo_path.rsplit("/", 1)[-1].lower()).strip("_") or "standin"
    return name if name[0].isalpha() else f"pkg_{name}"


def package_files(package: str, executables: list[str], marker: str = "") -> dict[str, str]:
    """An ament_python package whose console scripts print that they are stand-ins."""
    scripts = ",\n".join(f"            '{exe} = {package}.standin:main'" for exe in executables)
    return {
        f"{package}/package.xml": (
            '<?xml version="1.0"?>\n<package format="3">\n'
            f"  <name>{package}</name>\n  <version>0.0.1</version>\n"
            f"  <description>{STANDIN_NOTE}: no robot code</description>\n"
            "  <maintainer email=\"sandbox@roslab.invalid\">roslab sandbox</maintainer>\n"
            "  <license>Apache-2.0</license>\n  <exec_depend>rclpy</exec_depend>\n"
            "  <export><build_type>ament_python</build_type></export>\n</package>\n"),
        f"{package}/setup.py": (
            "from setuptools import setup\n\n"
            f"setup(\n    name='{package}',\n    version='0.0.1',\n    packages=['{package}'],\n"
            f"    data_files=[('share/ament_index/resource_index/packages', ['resource/{package}']),\n"
            f"                ('share/{package}', ['package.xml'])],\n"
            "    install_requires=['setuptools'],\n    zip_safe=True,\n"
            f"    description='{STANDIN_NOTE}',\n    license='Apache-2.0',\n"
            f"    entry_points={{'console_scripts': [\n{scripts},\n        ]}},\n)\n"),
        f"{package}/setup.cfg": (f"[develop]\nscript_dir=$base/lib/{package}\n"
                                 f"[install]\ninstall_scripts=$base/lib/{package}\n"),
        f"{package}/resource/{package}": "",
        f"{package}/{package}/__init__.py": "",
        f"{package}/{package}/standin.py": (
            f'"""{STANDIN_NOTE}: prints what it is and exits."""\n\n\n'
            f"def main():\n    print('{STANDIN_NOTE}: {package} {marker}'.strip())\n"),
        "README.md": f"# {STANDIN_NOTE}\n\nServed by the roslab sandbox upstream in place of the real repository.\n",
    }


def commit(bare: Path, files: dict[str, str], message: str, tags=(), move_tags: bool = False) -> str:
    """Commit `files` (the whole tree) on the bare repository's main branch; tag it; publish.

    Returns the new commit. `move_tags`: a tag that exists is moved (a test of a moved tag).
    """
    bare = Path(bare)
    if not (bare / "HEAD").is_file():
        bare.mkdir(parents=True, exist_ok=True)
        _git("init", "--quiet", "--bare", "--initial-branch=main", bare)
    work = bare.with_name(bare.name + ".work")
    subprocess.run(["rm", "-rf", str(work)], check=True)
    for relative, text in files.items():
        path = work / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    # The bare repository's objects, written from a throw-away index and work tree.
    index = {"GIT_INDEX_FILE": str(work) + ".index"}
    _git("--git-dir", bare, "--work-tree", work, "add", "-A", ".", cwd=work, env=index)
    tree = _git("--git-dir", bare, "write-tree", env=index)
    parent = _git("--git-dir", bare, "rev-parse", "refs/heads/main") if _has_main(bare) else ""
    made = _git("--git-dir", bare, "commit-tree", tree, *(["-p", parent] if parent else []), "-m", message)
    _git("--git-dir", bare, "update-ref", "refs/heads/main", made)
    subprocess.run(["rm", "-rf", str(work), str(work) + ".index"], check=True)
    for tag in tags:
        _git("--git-dir", bare, "tag", *(["-f"] if move_tags else []), tag, made)
    _git("--git-dir", bare, "update-server-info")
    return made


def _has_main(bare: Path) -> bool:
    try:
        _git("--git-dir", bare, "rev-parse", "--verify", "--quiet", "refs/heads/main")
        return True
    except RuntimeError:
        return False


def standin_repository(serve_dir: Path, url: str, repo_path: str, tags=(), packages=None) -> tuple[Path, str]:
    """Serve a stand-in for `url` (one commit, `tags` on it) unless it is served already.

    `packages`: {package: [executables]}; default one package named from `repo_path`.
    Returns (the bare repository, its main commit).
    """
    bare = Path(serve_dir) / served_path(url)
    packages = packages or {package_name(repo_path): [package_name(repo_path)]}
    if _has_main(bare):
        head = _git("--git-dir", bare, "rev-parse", "refs/heads/main")
        for tag in tags:
            try:
                _git("--git-dir", bare, "rev-parse", "--verify", "--quiet", f"refs/tags/{tag}")
            except RuntimeError:
                _git("--git-dir", bare, "tag", tag, head)
        _git("--git-dir", bare, "update-server-info")
        return bare, head
    files: dict[str, str] = {}
    for package, executables in packages.items():
        files.update(package_files(package, executables))
    return bare, commit(bare, files, f"{STANDIN_NOTE} for {url}", tags)


def rewrites(upstream_url: str, hosts=("github.com", "gitlab.com", "bitbucket.org")) -> dict[str, str]:
    """`source_url_rewrites` for the sandbox roster: each git host to the upstream's /git/."""
    return {f"https://{name}/": f"{upstream_url}/{GIT_ROOT}/{name}/" for name in hosts}


# A commit pin cannot be made: its stand-in carries this tag instead, and the sandbox roster
# pins the repository to it with `source_pins` (the setting a teacher uses to move a pin).
STANDIN_TAG = "roslab-sandbox-standin"
# What the built-in profiles run from their repositories, so that the stand-in has it:
# {repository path: {package: [executables]}} (default: one package named from the path).
STANDIN_PACKAGES = {
    "micro-ROS-Agent": {"micro_ros_agent": ["micro_ros_agent"]},
    "Micro-XRCE-DDS-Agent": {"microxrcedds_agent": ["MicroXRCEAgent"]},
    "osr-rover-code": {"osr_bringup": ["osr_bringup"]},
}


def content_key() -> str:
    """A digest of what the stand-ins hold: it changes when their files do (their commits too)."""
    import hashlib

    files = {package: package_files(package, executables) for packages in STANDIN_PACKAGES.values()
             for package, executables in packages.items()}
    files["<default>"] = package_files("standin", ["standin"])
    return hashlib.sha256(repr(sorted((k, sorted(v.items())) for k, v in files.items())).encode()).hexdigest()


def repositories(repos_files):
    """(repository path, URL, version) of each http(s) repository the .repos files name."""
    import yaml

    for path in repos_files:
        data = yaml.safe_load(Path(path).read_text()) or {}
        for repo_path, spec in (data.get("repositories") or {}).items():
            url = spec.get("url", "")
            if url.startswith(("http://", "https://")):
                yield repo_path, url, str(spec.get("version", ""))


def from_repos_files(serve_dir: Path, repos_files, skip=()) -> list[str]:
    """Stand-ins for every repository the .repos files name (the built-in profiles'), but the
    URLs in `skip` (served for real, real_sources.py); returns the URLs served. A tag pin is made
    on the stand-in's commit; a commit pin cannot be made (see the module doc), so such a
    stand-in carries STANDIN_TAG (see `commit_pins`)."""
    served = []
    for repo_path, url, version in repositories(repos_files):
        if url in skip:
            continue
        tags = [STANDIN_TAG] if re.fullmatch(r"[0-9a-f]{40}", version) else [version] if version else []
        standin_repository(serve_dir, url, repo_path, tags=tags, packages=STANDIN_PACKAGES.get(repo_path))
        served.append(url)
    return served


def commit_pins(repos_files, real=()) -> dict[str, str]:
    """`source_pins` for the sandbox roster: each commit-pinned repository to its stand-in's tag
    (a repository served for real, URL in `real`, keeps its real pin)."""
    return {repo_path: STANDIN_TAG for repo_path, url, version in repositories(repos_files)
            if re.fullmatch(r"[0-9a-f]{40}", version) and url not in real}
