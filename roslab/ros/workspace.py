"""pyinfra facts and operations for a colcon workspace that roslab fills from `nodes/`.

Used by `deploy/workspace.py` (and the unit facts by `roslab verify`). The design goals,
and why the operations look the way they do:

- One remote command reads the whole managed tree (checksums, modes, owners), not
  one fact per file: on a classroom of a dozen Pis that is the difference between a
  re-run of seconds and one of minutes. `files.sync` would ask per file, and its
  `delete=True` would also remove a student's own packages from `src/`.
- roslab only ever touches the package directories it manages, listed in
  `src/.roslab-manifest`: a package removed from `nodes/` is removed from the host,
  a student's own package beside it is never touched.
- Rebuilds and `rosdep install` are gated on stamps kept on the host (the hash of
  the sources of the last *successful* run). pyinfra evaluates operations again
  when it executes them, so these facts are read after the sync has run; a build
  that failed or was interrupted left no stamp and is retried on the next run.
- Classroom accidents heal on the next run, each named in one line: a workspace a
  student chowned to root is given back to the login user (`owned`), a node with a
  Python syntax error fails its host's build with file and line before colcon runs
  (`built`), and a nodes unit that gave up is started again (`NodesUnitState`).
"""

from __future__ import annotations

import hashlib
import io
import os
import posixpath
import re
import shlex
from dataclasses import dataclass, field, replace
from pathlib import Path

from pyinfra import host, logger, state
from pyinfra.api import FactBase, FileUploadCommand, OperationError, StringCommand, operation
from pyinfra.facts.files import FileContents
from pyinfra.operations.util.files import generate_color_diff
from roslab.controller_files import file_sha256
from roslab.ros import colcon_progress

MANIFEST_NAME = ".roslab-manifest"
MANIFEST_HEADER = (
    "# managed by roslab: the packages below are copies of the roslab checkout's nodes/.\n"
    "# roslab overwrites edits inside them and removes them when they leave nodes/;\n"
    "# packages of your own beside them in src/ are never touched.\n"
)

# The systemd unit that runs the role's launch.
NODES_SERVICE = "roslab-nodes.service"
NODES_UNIT_PATH = f"/etc/systemd/system/{NODES_SERVICE}"

# roslab's state in the workspace: stamps of the last successful rosdep install / build.
STATE_DIR_NAME = ".roslab"
BUILD_LOG_NAME = "roslab-build.log"
BUILD_LOG_TAIL_LINES = 40

# ROS package names (REP 144): lowercase letters, digits and underscores. Anything
# else in the manifest is ignored rather than handed to `rm -rf`.
PACKAGE_NAME = re.compile(r"^[a-z][a-z0-9_]*$")

# Never copied to hosts: byte-code and the output of a local `colcon build` or test run.
EXCLUDED_NAMES = {"__pycache__", ".pytest_cache", ".mypy_cache", "build", "install", "log"}
EXCLUDED_SUFFIXES = (".pyc", ".pyo", "~", ".swp")


# Controller side: what nodes/ holds
# ----------------------------------


@dataclass(frozen=True)
class LocalFile:
    path: str  # absolute path on the controller
    sha256: str
    mode: str  # "644" or "755": only the owner's execute bit carries over


def _is_excluded(name: str) -> bool:
    return name in EXCLUDED_NAMES or name.endswith(EXCLUDED_SUFFIXES)


def local_packages(nodes_dir: str | os.PathLike) -> dict[str, dict[str, LocalFile]]:
    """The packages in `nodes_dir`: {package: {path relative to nodes_dir: LocalFile}}.

    A package is a top-level directory holding a `package.xml`. Symlinks are not
    followed (a workspace should not depend on the controller's layout).
    """
    root = Path(nodes_dir)
    if not root.is_dir():
        raise OperationError(f"workspace_nodes_dir {str(root)!r} is not a directory")
    packages: dict[str, dict[str, LocalFile]] = {}
    for package_dir in sorted(root.iterdir()):
        if not (package_dir / "package.xml").is_file() or package_dir.is_symlink():
            continue
        if not PACKAGE_NAME.match(package_dir.name):
            raise OperationError(
                f"{package_dir}: {package_dir.name!r} is not a valid ROS package name "
                "(lowercase letters, digits and underscores)"
            )
        files = {}
        root_prefix = len(str(root)) + 1  # os.walk's dirpath starts with package_dir, under root
        for dirpath, dirnames, filenames in os.walk(package_dir):
            dirnames[:] = sorted(d for d in dirnames if not _is_excluded(d))
            relative_dir = dirpath[root_prefix:]
            for filename in sorted(filenames):
                full = os.path.join(dirpath, filename)
                if _is_excluded(filename) or os.path.islink(full):
                    continue
                mode = "755" if os.stat(full).st_mode & 0o100 else "644"
                files[f"{relative_dir}/{filename}"] = LocalFile(full, file_sha256(full), mode)
        packages[package_dir.name] = files
    if not packages:
        raise OperationError(f"workspace_nodes_dir {str(root)!r} holds no ROS packages")
    return packages


def tree_hash(packages: dict[str, dict[str, LocalFile]], only: str | None = None) -> str:
    """A hash of every file's path, content and mode (or only of files named `only`)."""
    digest = hashlib.sha256()
    for package in sorted(packages):
        for relative, local in sorted(packages[package].items()):
            if only and posixpath.basename(relative) != only:
                continue
            digest.update(f"{relative}\0{local.sha256}\0{local.mode}\n".encode())
    return digest.hexdigest()


def manifest_text(package_names) -> str:
    return MANIFEST_HEADER + "".join(f"{name}\n" for name in sorted(package_names))


def workspace_path(home: str, workspace_dir: str) -> str:
    """The workspace on the host: `workspace_dir` (`~/...`, schema-checked) under `home`.

    An absolute `workspace_dir` (only a `pyinfra --data` override can give one: the
    roster's schema wants `~/`) is taken as it is.
    """
    if workspace_dir == "~" or workspace_dir.startswith("~/"):
        workspace_dir = posixpath.join(home, workspace_dir[2:])
    return posixpath.normpath(workspace_dir)


# Host side: what the workspace's src/ holds
# -------------------------------------------


@dataclass(frozen=True)
class RemoteEntry:
    kind: str  # find's %y: f (file), d (directory), l (symlink), ...
    mode: str
    owner: str
    group: str
    sha256: str | None = None


class WorkspacePackages(FactBase):
    """
    The packages roslab manages in a workspace's `src/`, in one remote command.

    Returns ``{"manifest": [package, ...], "group": <user's primary group>,
    "entries": {path relative to src: RemoteEntry}}`` covering the packages named in
    the manifest and those passed in ``packages``; an empty dict if `src/` is missing.
    """

    @staticmethod
    def default():
        return {}

    def command(self, src_dir: str, packages: list[str], user: str) -> str:
        for name in packages:
            if not PACKAGE_NAME.match(name):
                raise OperationError(f"not a ROS package name: {name!r}")
        manifest = shlex.quote(MANIFEST_NAME)
        return "\n".join(
            [
                f"cd {shlex.quote(src_dir)} 2>/dev/null || exit 0",
                f"echo '## group'; id -gn {shlex.quote(user)}",
                f"echo '## manifest'; cat {manifest} 2>/dev/null",
                f"managed=$(grep -sxE '[a-z][a-z0-9_]*' {manifest} | sort -u)",
                "echo '## entries'",
                f"for p in $managed {' '.join(packages)}; do",
                "  [ -e \"$p\" ] && find \"$p\" -printf '%y %m %u %g %p\\n'",
                "done",
                "echo '## sums'",
                f"for p in $managed {' '.join(packages)}; do",
                "  [ -d \"$p\" ] && find \"$p\" -type f -exec sha256sum {} +",
                "done",
                "true",
            ]
        )

    def process(self, output):
        if not output:
            return {}
        sections: dict[str, list[str]] = {}
        current = None
        for line in output:
            if line.startswith("## "):
                current = sections.setdefault(line[3:].strip(), [])
            elif current is not None:
                current.append(line)
        entries: dict[str, RemoteEntry] = {}
        for line in sections.get("entries", []):
            kind, mode, owner, group, path = line.split(" ", 4)
            entries[path] = RemoteEntry(kind, mode, owner, group)
        for line in sections.get("sums", []):
            digest, path = _parse_sha256sum_line(line)
            if path in entries:
                entries[path] = replace(entries[path], sha256=digest)
        manifest = [
            line.strip() for line in sections.get("manifest", []) if PACKAGE_NAME.match(line.strip())
        ]
        group = (sections.get("group") or [""])[0].strip()
        return {"manifest": manifest, "group": group, "entries": entries}


def _parse_sha256sum_line(line: str) -> tuple[str, str]:
    # sha256sum escapes names holding a backslash or newline and marks the line with "\".
    if line.startswith("\\"):
        digest, path = line[1:].split("  ", 1)
        return digest, path.replace("\\n", "\n").replace("\\\\", "\\")
    digest, path = line.split("  ", 1)
    return digest, path


@dataclass
class SyncPlan:
    """What to do to make src/ match nodes/, all paths relative to src/."""

    remove_packages: list[str] = field(default_factory=list)
    remove_paths: list[str] = field(default_factory=list)
    make_dirs: list[str] = field(default_factory=list)
    upload: list[str] = field(default_factory=list)
    chmod: list[tuple[str, str]] = field(default_factory=list)
    chown_packages: list[str] = field(default_factory=list)
    write_manifest: bool = False

    def is_empty(self) -> bool:
        return not any(
            (self.remove_packages, self.remove_paths, self.make_dirs, self.upload, self.chmod,
             self.chown_packages, self.write_manifest)
        )


def plan_sync(local: dict[str, dict[str, LocalFile]], remote: dict, user: str) -> SyncPlan:
    """Compare nodes/ (local) with the WorkspacePackages fact (remote): a pure function."""
    plan = SyncPlan()
    entries: dict[str, RemoteEntry] = remote.get("entries", {})
    group = remote.get("group") or user

    plan.remove_packages = sorted(set(remote.get("manifest", [])) - set(local))
    plan.write_manifest = remote.get("manifest") != sorted(local)

    for package, files in sorted(local.items()):
        wanted_dirs = {package}
        for relative in files:
            parent = posixpath.dirname(relative)
            while parent and parent not in wanted_dirs:
                wanted_dirs.add(parent)
                parent = posixpath.dirname(parent)

        in_package = {
            path: entry
            for path, entry in entries.items()
            if path == package or path.startswith(package + "/")
        }
        # Anything that is not what we want at its path goes: extra files, links,
        # a file where a directory should be and the reverse.
        unwanted = sorted(
            path
            for path, entry in in_package.items()
            if entry.kind != ("f" if path in files else "d" if path in wanted_dirs else None)
        )
        removed: list[str] = []
        for path in unwanted:  # sorted: a directory comes before what is below it
            if not any(path.startswith(gone + "/") for gone in removed):
                removed.append(path)
        plan.remove_paths.extend(removed)
        kept = {
            path: entry
            for path, entry in in_package.items()
            if not any(path == gone or path.startswith(gone + "/") for gone in removed)
        }

        make_dirs = sorted(d for d in wanted_dirs if d not in kept)
        plan.make_dirs.extend(make_dirs)
        uploads = []
        for relative, local_file in sorted(files.items()):
            entry = kept.get(relative)
            if entry is None or entry.sha256 != local_file.sha256:
                uploads.append(relative)
                plan.chmod.append((relative, local_file.mode))
            elif entry.mode != local_file.mode:
                plan.chmod.append((relative, local_file.mode))
        plan.upload.extend(uploads)
        owned_wrong = any(entry.owner != user or entry.group != group for entry in kept.values())
        if uploads or make_dirs or owned_wrong:
            plan.chown_packages.append(package)
    return plan


@operation()
def packages(nodes_dir: str, src_dir: str, user: str):
    """
    Make the ROS packages of a local directory present, and exactly so, in a workspace's src/.

    + nodes_dir: local (controller) directory whose top-level packages are copied
    + src_dir: the workspace's ``src`` directory on the host (absolute)
    + user: owner of the copied files (group: the user's primary group)

    Only files that differ are uploaded; files that vanished from ``nodes_dir`` are
    removed, and so are whole packages that roslab put there before but that are no
    longer in ``nodes_dir`` (listed in ``src/.roslab-manifest``). Other packages in
    ``src/`` are left alone.

    **Example:**

    .. code:: python

        workspace.packages(
            name="Ensure the demo packages are in ~/ros2_ws/src",
            nodes_dir="nodes",
            src_dir="/home/ubuntu/ros2_ws/src",
            user="ubuntu",
        )
    """
    local = local_packages(nodes_dir)
    remote = host.get_fact(WorkspacePackages, src_dir=src_dir, packages=sorted(local), user=user)
    plan = plan_sync(local, remote, user)
    local_files = {rel: f for files in local.values() for rel, f in files.items()}

    if plan.is_empty():
        host.noop(f"packages {', '.join(sorted(local))} in {src_dir} match {nodes_dir}")
        return

    def remote_path(relative: str) -> str:
        return posixpath.join(src_dir, relative)

    if state.config.DIFF:
        _log_sync_diff(plan, local_files, remote, remote_path)

    yield from _sync_commands(plan, local, local_files, remote_path, user)


def _sync_commands(plan: SyncPlan, local: dict, local_files: dict, remote_path, user: str):
    """The commands that carry out `plan`: removals first, then folders, uploads, modes, the
    manifest, and owners last (over everything the plan touched)."""
    removals = [remote_path(p) for p in plan.remove_packages + plan.remove_paths]
    if removals:
        yield StringCommand("rm", "-rf", "--", *(shlex.quote(p) for p in removals))
    if plan.make_dirs:
        yield StringCommand("mkdir", "-p", "--", *(shlex.quote(remote_path(d)) for d in plan.make_dirs))
    for relative in plan.upload:
        dest = remote_path(relative)
        yield FileUploadCommand(
            local_files[relative].path,
            dest,
            remote_temp_filename=host.get_temp_filename(dest),
        )
    for mode in sorted({mode for _, mode in plan.chmod}):
        paths = [shlex.quote(remote_path(p)) for p, m in plan.chmod if m == mode]
        yield StringCommand("chmod", mode, "--", *paths)
    if plan.write_manifest:
        yield from _manifest_commands(local, remote_path, user)
    if plan.chown_packages:
        paths = [shlex.quote(remote_path(p)) for p in plan.chown_packages]
        yield StringCommand("chown", "-R", f"{shlex.quote(user)}:", "--", *paths)


def _manifest_commands(local: dict, remote_path, user: str):
    """Write src/.roslab-manifest, the list of packages roslab put there (so it removes only those later)."""
    manifest = remote_path(MANIFEST_NAME)
    yield FileUploadCommand(
        io.StringIO(manifest_text(local)),
        manifest,
        remote_temp_filename=host.get_temp_filename(manifest),
    )
    yield StringCommand("chmod", "644", shlex.quote(manifest))
    yield StringCommand("chown", f"{shlex.quote(user)}:", shlex.quote(manifest))


def _log_sync_diff(plan: SyncPlan, local_files, remote, remote_path) -> None:
    for path in plan.remove_packages + plan.remove_paths:
        host.log(f"Will remove {remote_path(path)}", logger.info)
    for relative in plan.upload:
        exists = relative in remote.get("entries", {}) and relative not in plan.remove_paths
        verb = "update" if exists else "create"
        host.log(f"Will {verb} {remote_path(relative)}", logger.info)
        try:
            desired = Path(local_files[relative].path).read_text().splitlines(keepends=True)
            current: list[str] = []
            if exists:
                current = (host.get_fact(FileContents, path=remote_path(relative)) or [])
                current = [line + "\n" for line in current]
            for line in generate_color_diff(current, desired):
                logger.info("  %s", line)
        except UnicodeDecodeError:
            logger.info("  (binary file)")


# Host side: who owns the workspace
# ----------------------------------

FOREIGN_EXAMPLES = 3


class WorkspaceForeign(FactBase):
    """
    Paths in a workspace that do not belong to its user (and the user's primary group).

    Returns ``{"count": n, "examples": [up to 3 paths relative to the workspace],
    "group": <the user's primary group, or None>}``; a count of 0 when every path does,
    or when there is no workspace yet (the group is read even then: the deploy creates
    the workspace's folders with it, so a fresh workspace is not "given back" later).
    The whole tree is read (build/, install/, log/, src/ and roslab's state): a student
    who ran `sudo colcon build` or `sudo chown -R root ~/ros2_ws` left root's files
    anywhere. Symbolic links are not followed.
    """

    @staticmethod
    def default():
        return {"count": 0, "examples": [], "group": None}

    def command(self, workspace_dir: str, user: str) -> str:
        ws, who = shlex.quote(workspace_dir), shlex.quote(user)
        return (
            f"group=$(id -gn {who}) || exit 0; echo \"group $group\"; [ -d {ws} ] || exit 0; "
            f"find {ws} \\( ! -user {who} -o ! -group \"$group\" \\) -printf '%P\\n' 2>/dev/null"
            f" | awk 'NR <= {FOREIGN_EXAMPLES} {{ print \"path \" $0 }} END {{ print \"count \" NR }}'"
        )

    def process(self, output):
        result = self.default()
        for line in output:
            kind, _, value = line.partition(" ")
            if kind == "count" and value.strip().isdigit():
                result["count"] = int(value)
            elif kind == "path":
                result["examples"].append(value or ".")
            elif kind == "group":
                result["group"] = value.strip() or None
        return result


@operation()
def owned(workspace_dir: str, user: str):
    """
    Give every path in a workspace back to its user (and the user's primary group).

    + workspace_dir: the workspace on the host (absolute)
    + user: the login user who owns it

    Runs ``chown -R`` (as root) only when some path belongs to someone else, and says
    how many and which in one line. ``chown -R`` does not follow symbolic links: a link
    a student made to a system file changes owner itself, never its target.
    """
    foreign = host.get_fact(WorkspaceForeign, workspace_dir=workspace_dir, user=user)
    if not foreign["count"]:
        host.noop(f"everything in {workspace_dir} belongs to {user}")
        return
    # One line per host and run: pyinfra may run this body when planning and again when
    # executing (with -y only then).
    reported = getattr(state, "roslab_reported", None)
    if reported is None:
        reported = set()
        setattr(state, "roslab_reported", reported)  # roslab's own note on pyinfra's State
    said = (host.name, getattr(host, "current_op_hash", None))
    if said not in reported:
        reported.add(said)
        examples = ", ".join(foreign["examples"])
        more = ", ..." if foreign["count"] > len(foreign["examples"]) else ""
        host.log(
            f"workspace: {foreign['count']} {'path' if foreign['count'] == 1 else 'paths'} in {workspace_dir}"
            f" {'does' if foreign['count'] == 1 else 'do'} not belong to {user} "
            f"({examples}{more}): giving them back",
            logger.warning,
        )
    yield StringCommand("chown", "-R", "--", f"{shlex.quote(user)}:", shlex.quote(workspace_dir))


# Host side: stamps of the last successful rosdep install and build
# ------------------------------------------------------------------


class WorkspaceStamps(FactBase):
    """
    What roslab last did successfully in a workspace.

    Returns ``{"rosdep": <hash or None>, "build": <hash or None>, "installed": bool}``:
    the stamps are hashes of the sources at the last successful `rosdep install` and
    `colcon build`; ``installed`` is whether ``install/setup.sh`` exists.
    """

    @staticmethod
    def default():
        return {"rosdep": None, "build": None, "installed": False}

    def command(self, workspace_dir: str) -> str:
        ws = shlex.quote(workspace_dir)
        state = shlex.quote(posixpath.join(workspace_dir, STATE_DIR_NAME))
        return (
            f"echo rosdep $(cat {state}/rosdep.sha256 2>/dev/null); "
            f"echo build $(cat {state}/build.sha256 2>/dev/null); "
            # colcon-core always writes setup.sh; setup.bash needs the colcon-bash extension.
            f"if [ -f {ws}/install/setup.sh ]; then echo installed yes; else echo installed no; fi"
        )

    def process(self, output):
        values = dict((line.split(" ", 1) + [""])[:2] for line in output)
        return {
            "rosdep": values.get("rosdep", "").strip() or None,
            "build": values.get("build", "").strip() or None,
            "installed": values.get("installed", "").strip() == "yes",
        }


def _write_stamp(path: str, value: str) -> str:
    return f"printf '%s\\n' {shlex.quote(value)} > {shlex.quote(path)}"


@operation()
def dependencies(
    workspace_dir: str, packages: list[str], distro: str, packages_hash: str, user: str,
    ros_home: str,
):
    """
    Install the system dependencies of a workspace's packages with rosdep, when they changed.

    + workspace_dir: the workspace on the host (absolute)
    + packages: the packages in its ``src`` whose dependencies are installed (roslab's:
      a student's package with an unknown key must not fail the classroom's deploy)
    + distro: ROS 2 distro the keys are resolved for
    + packages_hash: hash of the ``package.xml`` files roslab manages; rosdep runs when it
      differs from the one of the last successful run
    + user: owner of the workspace (and of the stamp)
    + ros_home: the user's ``~/.ros``, where ``rosdep update`` left its cache

    Runs as root (apt), reading the user's rosdep cache through ``ROS_HOME``.
    """
    stamp = packages_hash + ":" + distro
    stamps = host.get_fact(WorkspaceStamps, workspace_dir=workspace_dir)
    if stamps.get("rosdep") == stamp:
        host.noop("rosdep has installed the dependencies of these package.xml files already")
        return
    state_dir = posixpath.join(workspace_dir, STATE_DIR_NAME)
    rosdep_stamp = posixpath.join(state_dir, "rosdep.sha256")
    # rosdep runs as root (apt); the stamp, like the rest of the workspace, is the user's and
    # is written as the user: root writing by path in the user's directory would follow a
    # link the user put there (and `chown` would give the link's target away).
    as_user = f"runuser -u {shlex.quote(user)} --"
    yield StringCommand(
        f"{as_user} mkdir -p {shlex.quote(state_dir)}",
        f"&& cd {shlex.quote(workspace_dir)}",
        f"&& ROS_HOME={shlex.quote(ros_home)} rosdep install --from-paths",
        *(shlex.quote(f"src/{name}") for name in packages),
        "--ignore-src -y",
        f"--rosdistro {shlex.quote(distro)}",
        f"&& {as_user} sh -c {shlex.quote(_write_stamp(rosdep_stamp, stamp))}",
    )


# Compiles every .py below the given directories with the host's python3 (the one colcon
# builds with), writing no byte-code: a syntax error names file and line before colcon
# runs, where an ament_python build would install the broken file and succeed.
PYTHON_SYNTAX_CHECK = """\
import os, sys, warnings
warnings.simplefilter("ignore")
bad = 0
for top in sys.argv[1:]:
    for folder, dirs, files in os.walk(top):
        dirs.sort()
        for name in sorted(files):
            if not name.endswith(".py"):
                continue
            path = os.path.join(folder, name)
            try:
                with open(path, "rb") as source:
                    compile(source.read(), path, "exec", dont_inherit=True)
            except (SyntaxError, ValueError) as error:
                bad += 1
                where = os.path.abspath(path) + ":" + str(getattr(error, "lineno", None) or 0)
                detail = getattr(error, "msg", None) or str(error)
                print(where + ": " + type(error).__name__ + ": " + detail, file=sys.stderr)
sys.exit(1 if bad else 0)
"""
SYNTAX_ERROR_EXIT = 65  # EX_DATAERR


def build_script(
    workspace_dir: str, distro: str, colcon_args: list[str], stamp: str, python_paths=(), underlays=(),
) -> str:
    """The bash script that builds the workspace, keeping its log, stamping success.

    `python_paths` (relative to the workspace) are compiled first: a syntax error there
    fails the build with file and line, before colcon runs, and leaves no stamp.
    `underlays`: setup.bash files sourced after the distro's (the underlay of deploy/sources.py).
    """
    state_dir = posixpath.join(workspace_dir, STATE_DIR_NAME)
    build_stamp = posixpath.join(state_dir, "build.sha256")
    log = posixpath.join("log", BUILD_LOG_NAME)
    colcon = " ".join(shlex.quote(arg) for arg in ["colcon", "build", *colcon_args])
    progress = colcon_progress.build_lines(colcon, log)
    syntax_check = []
    if python_paths:
        paths = " ".join(shlex.quote(path) for path in python_paths)
        syntax_check = [
            f"if ! python3 -B -c {shlex.quote(PYTHON_SYNTAX_CHECK)} {paths}; then",
            "  echo \"workspace: not built: fix the Python file named above where roslab copies it"
            " from (workspace_nodes_dir, by default the checkout's nodes/) and run again\" >&2",
            f"  exit {SYNTAX_ERROR_EXIT}",
            "fi",
        ]
    return "\n".join(
        [
            f"cd {shlex.quote(workspace_dir)} || exit 1",
            f"mkdir -p log {shlex.quote(state_dir)}",
            # No stamp while building: an interrupted build is retried on the next run.
            f"rm -f {shlex.quote(build_stamp)}",
            f"source /opt/ros/{shlex.quote(distro)}/setup.bash || exit 1",
            *(f"source {shlex.quote(setup)} || exit 1" for setup in underlays),
            *syntax_check,
            progress[0],  # how many packages: the run's "still running" line counts them (colcon_progress)
            f"if {progress[1]}; then",
            f"  {_write_stamp(build_stamp, stamp)}",
            "else",
            "  status=$?",
            f"  echo \"colcon build failed (exit $status); the last {BUILD_LOG_TAIL_LINES} lines of"
            f" {posixpath.join(workspace_dir, log)}:\" >&2",
            f"  tail -n {BUILD_LOG_TAIL_LINES} {log} >&2",
            "  exit $status",
            "fi",
        ]
    )


@operation()
def built(
    workspace_dir: str, distro: str, colcon_args: list[str], sources_hash: str, python_paths=(), underlays=(),
):
    """
    Build a colcon workspace when its sources changed since the last successful build.

    + workspace_dir: the workspace on the host (absolute)
    + distro: ROS 2 distro whose ``/opt/ros/<distro>/setup.bash`` is sourced for the build
    + colcon_args: arguments after ``colcon build``
    + sources_hash: hash of the sources roslab manages
    + python_paths: directories (relative to the workspace) whose ``.py`` files must
      compile before colcon runs (roslab's packages)
    + underlays: setup.bash files of underlay workspaces, sourced after the distro's

    Run it as the workspace's owner (``_sudo_user``). The build's output goes to
    ``log/roslab-build.log`` in the workspace; when the build fails its tail is the
    operation's error output, and a Python syntax error fails it with file and line
    before colcon runs. A build is needed when the stamp of the last successful
    build (sources, distro and arguments) differs or ``install/setup.sh`` is missing.
    """
    stamp = hashlib.sha256(
        "\0".join([sources_hash, distro, *colcon_args]).encode()
    ).hexdigest()
    stamps = host.get_fact(WorkspaceStamps, workspace_dir=workspace_dir)
    if stamps.get("build") == stamp and stamps.get("installed"):
        host.noop(f"{workspace_dir} is built from these sources already")
        return
    script = build_script(workspace_dir, distro, colcon_args, stamp, python_paths, underlays)
    yield StringCommand("bash", "-c", shlex.quote(script))


# Host side: the nodes' unit
# --------------------------


class NodesUnitState(FactBase):
    """
    One unit's state as systemd has it: ``{"LoadState": ..., "ActiveState": ..., "SubState": ...,
    "Result": ...}`` (e.g. loaded, failed, failed, start-limit-hit).

    Asks about this unit only (``systemctl show -p ... <unit>``), never every unit.
    """

    @staticmethod
    def default():
        return {}

    def requires_command(self, service: str = NODES_SERVICE) -> str:
        return "systemctl"

    def command(self, service: str = NODES_SERVICE) -> str:
        return f"systemctl show --property=LoadState,ActiveState,SubState,Result {shlex.quote(service)}"

    def process(self, output):
        return dict(line.split("=", 1) for line in output if "=" in line)


def stopped_reason(unit_state: dict) -> str | None:
    """Why a loaded unit that should run is not running and would not start by itself, or None.

    failed: it gave up (its start limit, or a crash with no restart left); inactive:
    someone stopped it. activating (auto-restart) is systemd still trying: left alone.
    """
    if unit_state.get("LoadState") != "loaded":
        return None  # not installed yet: writing the unit starts it
    active = unit_state.get("ActiveState")
    if active == "failed":
        result = unit_state.get("Result")
        return f"failed ({result})" if result and result != "success" else "failed"
    if active == "inactive":
        return "inactive (stopped)"
    return None


@operation()
def restarted(service: str):
    """
    Restart a systemd service, even one that gave up after hitting its start limit.

    + service: the unit, e.g. ``roslab-nodes.service``

    Always restarts: gate it with ``_if`` on what the service depends on.
    """
    unit = shlex.quote(service)
    # reset-failed forgets earlier failures, or systemd refuses "start request repeated too quickly".
    yield f"systemctl reset-failed {unit} 2>/dev/null; systemctl restart {unit}"
