"""Source workspaces: vcstool `.repos` files, read and checked before any host is touched.

A `.repos` file (vcstool's format) lists repositories by the path they take in a workspace's
`src/`::

    repositories:
      osr-rover-code:
        type: git
        url: https://github.com/nasa-jpl/osr-rover-code.git
        version: 3f4a...   # a 40-hex commit, or a tag: what the class builds is pinned

A robot profile's side names its files (`sources:`, beside a built-in profile's YAML or
relative to the roster for a roster's profile), a roster adds its own (`workspace_sources`,
relative to the roster). Every problem names the file and line, the host and the field; a
version that only the upstream can tell is a branch (not a tag) is refused by the controller's
fetch (roslab/sources/fetch.py), naming file, repository and field too.

The loader puts the repositories into host data as plain dicts (`REPOSITORY_KEYS`):
`roslab_profile["sources"]` (the profile's) and `roslab_sources` (the profile's and the
roster's, what deploy/sources.py builds in the login user's underlay workspace).
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from urllib.parse import urlsplit

from roslab.ros import distro as distros
from roslab.controller_files import kind_of
from roslab.formats import Context, describe, file_url_problem, within
from roslab.checked.loading import line_of, load_yaml
from roslab.checked.problems import Problem, Report, display_path

# A .repos file's name as a profile or roster gives it: a relative path ending in .repos.
REPOS_FILE = re.compile(r"(?:[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}/){0,7}[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}\.repos",
                        re.ASCII)
# A repository's path in src/: relative, each part starting with a letter, digit or _ (so no
# `..`, no hidden folders, no absolute path), at most 8 parts.
REPO_PATH = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}(?:/[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}){0,7}", re.ASCII)
COMMIT = re.compile(r"[0-9a-f]{40}", re.ASCII)
# A tag as git accepts it (git check-ref-format), narrowed to what a release tag looks like.
TAG = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}(?:/[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}){0,3}", re.ASCII)
# Names that are branches in every ROS repository (and ROS distros, which name branches):
# refused without asking upstream. Any other name is asked: a branch there is refused too.
# The distros roslab has records of are added from roslab.ros.distro (`branch_names()`), so a new
# record needs no edit here.
_BRANCH_NAMES = frozenset({
    "HEAD", "master", "main", "develop", "devel", "development", "trunk", "rolling", "ros2", "ros2-devel",
    "ardent", "bouncy", "crystal", "dashing", "eloquent", "foxy", "galactic", "iron",
})


def branch_names() -> frozenset[str]:
    """The names refused as pins without asking upstream: the usual branches and every ROS distro's."""
    return _BRANCH_NAMES | set(distros.BY_NAME)

URL_SCHEMES = ("http", "https", "file")
MAX_REPOSITORIES = 200
MAX_URL = 2000
REPOSITORY_KEYS = ("path", "type", "url", "version", "file", "line")


class RepositoryProblem(Exception):
    """One problem of a .repos file: the message and the line."""

    def __init__(self, message: str, line: int | None = None):
        super().__init__(message)
        self.line = line


def _url_text(text: str) -> bool:
    """One line of printable ASCII without spaces, at most MAX_URL characters: what a URL or
    a URL prefix is before its parts are looked at (git, logs and the lock file take it as is)."""
    return (text.isascii() and len(text) <= MAX_URL
            and not any(char.isspace() or ord(char) < 32 or char == "\x7f" for char in text))


def url_problem(url, repos_dir: Path | None = None) -> str | None:
    """Why `url` cannot be a repository's URL, or None.

    http(s) or file:// only (git's ssh:// and scp-like forms would need a key on the
    controller); no user or password in it (it is printed, logged and kept in the lock file);
    a file:// URL must lead inside the folder of the .repos file that names it (what the
    controller fetches is copied to every Pi: never a repository elsewhere on this machine).
    """
    if not isinstance(url, str):
        return f"must be a URL (a string), not {url!r}"
    if not _url_text(url):
        return f"{url!r} is not a URL (ASCII without spaces, at most {MAX_URL} characters)"
    parts = urlsplit(url)
    if parts.scheme not in URL_SCHEMES:
        return f"{url!r}: only {', '.join(s + '://' for s in URL_SCHEMES)} URLs are fetched"
    if "@" in parts.netloc:
        return f"{url!r} holds a user name or password: give the repository's public URL"
    if parts.scheme in ("http", "https") and not parts.hostname:
        return f"{url!r} names no host"
    if parts.query or parts.fragment:
        return f"{url!r}: a repository URL has no ?query or #fragment"
    if parts.scheme == "file":
        if parts.netloc not in ("", "localhost"):
            return f"{url!r}: a file:// URL names a path on this machine (file:///...)"
        if repos_dir is not None:
            return file_url_problem(url, repos_dir, "the folder of its .repos file")
    return None


def version_problem(version) -> str | None:
    """Why `version` is not a pin (a 40-hex commit or a tag), or None."""
    if isinstance(version, bool) or isinstance(version, (int, float)):
        return f"must be a commit or a tag (a string), not {version!r}: quote it"
    if not isinstance(version, str) or not version:
        return "must be the commit (40 hex digits) or the tag the class builds"
    if COMMIT.fullmatch(version):
        return None
    if re.fullmatch(r"[0-9a-fA-F]{7,39}", version) and not re.fullmatch(r"[0-9]+", version):
        return (f"{version!r} looks like an abbreviated commit: give all 40 hex digits "
                "(a short one can match another commit later)")
    if version in branch_names() or version.startswith(("refs/heads/", "origin/")):
        return (f"{version!r} is a branch, which moves: pin the commit (40 hex digits) or a tag, "
                "so every Pi of the class builds the same sources")
    if not TAG.fullmatch(version) or ".." in version or version.endswith((".lock", ".", "/")) \
            or "@{" in version:
        return f"{version!r} is neither a commit (40 hex digits) nor a tag name"
    return None


def parse_repos(path: Path, report: Report) -> list[dict]:
    """The repositories of one .repos file (dicts of REPOSITORY_KEYS); problems to `report`
    (whose path is the file), each with its line."""
    repositories = _repositories_mapping(path, report)
    if repositories is None:
        return []
    repos_dir = Path(path).resolve().parent
    result = []
    seen: dict[str, str] = {}
    for name, spec in repositories.items():
        field = f"repositories.{name}"
        line = line_of(repositories, name)
        if not _repository_path_ok(name, seen, report, line, field):
            continue
        if not isinstance(spec, dict):
            report.error("must be a mapping {type: git, url, version}", line=line, field=field)
            continue
        if _repository_spec_ok(spec, repos_dir, report, line, field):
            result.append({"path": name, "type": "git", "url": spec["url"], "version": spec["version"],
                           "file": display_path(path), "line": line_of(spec, "version") or line})
    return result


def _repositories_mapping(path: Path, report: Report):
    """The file's `repositories:` mapping; None (reported) when the file is not a .repos file
    roslab can read. Unknown top-level keys and repeated repositories are reported, not fatal."""
    mapping = load_yaml(path, report)
    if report.errors:
        return None
    if not isinstance(mapping, dict) or "repositories" not in mapping:
        report.error("is not a vcstool .repos file: it needs a top-level 'repositories:' mapping of "
                     "path -> {type: git, url, version}", line=line_of(mapping) if mapping else None)
        return None
    for key in mapping:
        if key != "repositories":
            report.error(f"unknown top-level key {key!r} (a .repos file holds 'repositories:')",
                         line=line_of(mapping, key), field=str(key))
    repositories = mapping["repositories"]
    if not isinstance(repositories, dict) or not repositories:
        report.error("'repositories' must be a mapping of path -> {type: git, url, version}",
                     line=line_of(mapping, "repositories"), field="repositories")
        return None
    if len(repositories) > MAX_REPOSITORIES:
        report.error(f"lists {len(repositories)} repositories; at most {MAX_REPOSITORIES}",
                     line=line_of(mapping, "repositories"), field="repositories")
        return None
    for key, dup_line, first in getattr(repositories, "duplicates", []):
        report.error(f"repository {key!r} appears twice (also at line {first})", line=dup_line,
                     field=f"repositories.{key}")
    return repositories


def _repository_path_ok(name, seen: dict[str, str], report: Report, line, field: str) -> bool:
    """Whether a repository's path is a safe folder in src/; one that overlaps another's
    (case-insensitively) is reported but still read, so its spec's problems show too."""
    if not isinstance(name, str) or not REPO_PATH.fullmatch(name) or ".." in name.split("/"):
        report.error(f"{name!r} is not a safe path in src/ (relative; letters, digits and _ . + -, "
                     "each part starting with a letter, digit or _)", line=line, field=field)
        return False
    lowered = name.lower()
    for other in seen:
        if lowered == other or lowered.startswith(other + "/") or other.startswith(lowered + "/"):
            report.error(f"{name!r} overlaps repository {seen[other]!r}: each takes a folder of its own",
                         line=line, field=field)
    seen[lowered] = name
    return True


def _repository_spec_ok(spec: dict, repos_dir: Path, report: Report, line, field: str) -> bool:
    """Whether a repository's {type, url, version} is one roslab fetches; every problem reported."""
    for key in spec:
        if key not in ("type", "url", "version"):
            report.error(f"unknown key {key!r} (a repository has type, url, version)",
                         line=line_of(spec, key), field=f"{field}.{key}")
    kind = spec.get("type")
    if kind != "git":
        report.error(f"type must be git (the only kind roslab fetches), not {kind!r}",
                     line=line_of(spec, "type") or line, field=f"{field}.type")
    problem = url_problem(spec.get("url"), repos_dir) if "url" in spec else "is missing: the repository's URL"
    if problem:
        report.error(problem, line=line_of(spec, "url") or line, field=f"{field}.url")
    vproblem: str | None
    if "version" not in spec:
        vproblem = "is missing: pin the commit (40 hex digits) or the tag the class builds"
    else:
        vproblem = version_problem(spec.get("version"))
    if vproblem:
        report.error(vproblem, line=line_of(spec, "version") or line, field=f"{field}.version")
    return kind == "git" and not problem and not vproblem


class ReposFiles:
    """The .repos files a roster's hosts name, each read once (a roster of 30 hosts sharing a
    file reads it once) and its problems reported once per host that needs it."""

    def __init__(self):
        self._read: dict[str, tuple[list[dict], list[Problem]]] = {}

    def read(self, path: Path) -> tuple[list[dict], list[Problem]]:
        key = os.path.realpath(path)
        if key not in self._read:
            report = Report(path)
            repositories = parse_repos(Path(path), report)
            self._read[key] = (repositories, list(report.errors))
        return self._read[key]


def name_problem(name, base_dir: Path) -> str | None:
    """Why `name` cannot name a .repos file below `base_dir`, or None."""
    if not isinstance(name, str):
        return f"must be a .repos file name (a string), not {name!r}"
    if not REPOS_FILE.fullmatch(name) or ".." in name.split("/"):
        return (f"{name!r} is not a .repos file name: a relative path ending in .repos (letters, digits "
                "and _ . -), inside the folder it is relative to")
    path = base_dir / name
    if not within(path, base_dir, strictly=False):
        return f"{name!r} leads outside {base_dir} (a link?)"
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return f"{name!r}: no such file ({path})"
    except OSError as exc:  # a symlink loop, a folder we may not enter
        return f"{name!r}: cannot read it ({path}): {exc.strerror or exc}"
    if not stat.S_ISREG(mode):
        return f"{name!r} ({path}) is {kind_of(mode)}, not a regular file"
    return None


def merged(groups: list[tuple[str, list[dict]]]) -> tuple[list[dict], list[str]]:
    """One list of repositories from several files (the profile's, then the roster's): the same
    path twice with another URL or version is a conflict (messages name both files)."""
    by_path: dict[str, dict] = {}
    problems = []
    for _field, repositories in groups:
        for repo in repositories:
            known = by_path.get(repo["path"])
            if known is None:
                by_path[repo["path"]] = repo
            elif (known["url"], known["version"]) != (repo["url"], repo["version"]):
                problems.append(f"repository {repo['path']!r} is {repo['url']} {repo['version']} in "
                                f"{repo['file']}:{repo['line']} but {known['url']} {known['version']} in "
                                f"{known['file']}:{known['line']}: a workspace holds one of them")
    return [by_path[path] for path in sorted(by_path)], problems


def rewritten(url: str, rewrites: dict[str, str] | None) -> str:
    """`url` with the longest matching prefix replaced, as git's `url.<base>.insteadOf` does."""
    best, table = "", rewrites or {}
    for prefix in table:
        if url.startswith(prefix) and len(prefix) > len(best):
            best = prefix
    return (table[best] + url[len(best):]) if best else url


def rewrites_problem(value, context=None) -> str | None:
    """A mapping of URL prefix -> URL prefix (http, https or file), each one line of ASCII; a
    file:// replacement leads inside the roster's folder (not .roslab-state), like a file://
    source: what the controller fetches is copied to every Pi."""
    context = context or Context()
    if not isinstance(value, dict):
        return "must be a mapping of URL prefix -> replacement prefix"
    for prefix, replacement in value.items():
        for text in (prefix, replacement):
            if not isinstance(text, str):
                return f"{text!r} must be a URL prefix (a string)"
            if not _url_text(text):
                return f"{text!r} is not a URL prefix (ASCII without spaces, at most {MAX_URL} characters)"
            parts = urlsplit(text)
            if parts.scheme not in URL_SCHEMES:
                return f"{text!r}: only http://, https:// and file:// prefixes"
            if "@" in parts.netloc:
                return f"{text!r} holds a user name or password"
        problem = file_url_problem(replacement, Path(context.roster_dir), "the roster's folder")
        if problem:
            return f"{prefix} -> {problem}"
    return None


describe(rewrites_problem, allowed="URL prefix: replacement prefix (http, https, file)")


def repos_file_problem(value, context=None) -> str | None:
    """A .repos file inside the roster's folder (relative to the roster)."""
    context = context or Context()
    return name_problem(value, Path(context.roster_dir))


describe(repos_file_problem, allowed="a .repos file, relative to the roster")


def pins_problem(value, _context=None) -> str | None:
    """Why `value` is not a mapping of repository path -> pin (a commit or a tag), or None."""
    if not isinstance(value, dict):
        return "must be a mapping of repository path (as in its .repos file) to a commit or a tag"
    if len(value) > MAX_REPOSITORIES:
        return f"has {len(value)} entries; at most {MAX_REPOSITORIES} are allowed"
    for path, version in value.items():
        if not isinstance(path, str) or not REPO_PATH.fullmatch(path) or ".." in path.split("/"):
            return f"{path!r} is not a repository's path (relative, letters, digits and _ . + -)"
        problem = version_problem(version)
        if problem:
            return f"{path}: {problem}"
    return None


def pinned(repositories: list[dict], pins: dict | None) -> list[dict]:
    """The repositories with the roster's `source_pins` in place of their files' versions (a
    teacher moves a pin, or a lab builds its mirror's tag, without editing a profile)."""
    return [{**repo, "version": pins[repo["path"]], "file": "source_pins", "line": None}
            if pins and repo["path"] in pins else repo for repo in repositories]


def host_sources(data: dict, profile_sources: list[tuple[Path, str]], roster_dir: Path,
                 files: ReposFiles) -> tuple[list[dict], list[dict], list[tuple[str, Problem | str]]]:
    """(the profile's repositories, every repository of the host, problems as (field, Problem or text)).

    `profile_sources`: the host's profile side's .repos files as (folder, name);
    `data["workspace_sources"]`: the roster's, relative to `roster_dir` (checked already).
    """
    problems: list[tuple[str, Problem | str]] = []
    profile_repos: list[dict] = []
    for folder, name in profile_sources:
        problem = name_problem(name, folder)
        if problem:
            problems.append(("sources", f"robot profile's sources: {problem}"))
            continue
        repositories, file_problems = files.read(folder / name)
        problems += [("sources", problem) for problem in file_problems]
        profile_repos += repositories
    roster_repos: list[dict] = []
    for name in data.get("workspace_sources") or []:
        repositories, file_problems = files.read(roster_dir / name)
        problems += [("workspace_sources", problem) for problem in file_problems]
        roster_repos += repositories
    profile_merged, conflicts = merged([("sources", profile_repos)])
    problems += [("sources", text) for text in conflicts]
    every, conflicts = merged([("sources", profile_merged), ("workspace_sources", roster_repos)])
    problems += [("workspace_sources", text) for text in conflicts]
    rewrites = data.get("source_url_rewrites") or {}
    for repo in every:
        url = rewritten(repo["url"], rewrites)
        problem = file_url_problem(url, roster_dir, "the roster's folder") if url != repo["url"] else None
        if problem:
            problems.append(("source_url_rewrites", f"repository {repo['path']!r} ({repo['url']}) is rewritten "
                                                    f"to {problem}"))
    pins = data.get("source_pins")
    return pinned(profile_merged, pins), pinned(every, pins), problems
