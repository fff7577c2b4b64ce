"""pyinfra facts and operations for the login user's underlay workspace (deploy/sources.py).

The underlay holds the third-party repositories of the host's .repos files, each extracted
from the archive the controller made of its pinned commit (roslab/sources/fetch.py) into
`src/<path>`; `.roslab/sources.json` records the sha256 of each extracted archive, so only a
changed repository is copied again, and a repository that left the .repos files is removed
(folders of `src/` that roslab did not put there are never touched).

The build keeps the last good install usable: colcon builds into an install tree named for
what it is built from (`install-<digest>`, `slot`; the same name on every host of a group, so a
tree shipped to another host lands where it was built: roslab/sources/ship.py), and `install`
is switched to it (one rename) only when the whole build succeeded; then the other trees go. A failed build leaves `install` where it
was, and the host fails with the package and its first error line. The build stamp (the
sha256 of every repository's archive, the distro and colcon's arguments) is written only
then, so an interrupted or failed build is tried again on the next run.
"""

from __future__ import annotations

import io
import json
import posixpath
import shlex

from pyinfra import host
from pyinfra.api import FactBase, FileUploadCommand, StringCommand, operation

from roslab.sources.repos import REPO_PATH
from roslab.ros import colcon_progress
from roslab.ros.workspace import STATE_DIR_NAME, WorkspaceStamps, _write_stamp

MANIFEST = f"{STATE_DIR_NAME}/sources.json"
# Where the archives wait (root's) between their upload and their extraction by the user.
ARCHIVE_DIR = "/var/lib/roslab/sources"
BUILD_LOG = "log/roslab-underlay-build.log"
# The profile's CMake settings per package, as colcon-metadata reads them (`--metas`); in
# roslab's own folder, so a colcon.meta the user keeps beside src/ is never touched.
COLCON_META = f"{STATE_DIR_NAME}/colcon.meta"
# Where each underlay records where its install came from: "built here <digest>" or
# "shipped from <host> <digest>" (`roslab status` shows it).
ORIGIN = f"{STATE_DIR_NAME}/underlay-origin"


def origin_line(digest: str, builder: str | None = None) -> str:
    return f"shipped from {builder} {digest}" if builder else f"built here {digest}"


def switch_script(slot: str) -> list[str]:
    """Shell lines making `install` point to `slot` (a shell word: `"$slot"`) in one rename and
    removing the other trees: the install trees and build folders of earlier builds."""
    q = slot
    return [
        # a real folder left by a hand-made build is replaced by the link (the link: one rename)
        'if [ -e install ] && [ ! -L install ]; then rm -rf install; fi',
        f"ln -sfn {q} install.roslab-new && mv -T install.roslab-new install",
        "for tree in install-* build-install-*; do",
        f'  case "$tree" in {q}|build-{q}) ;; *) [ -e "$tree" ] && rm -rf "$tree" ;; esac',
        "done",
    ]


def _checked_paths(paths) -> list[str]:
    paths = list(paths)
    for path in paths:
        if not REPO_PATH.fullmatch(path) or ".." in path.split("/"):
            raise ValueError(f"not a repository path: {path!r}")
    return list(paths)


class UnderlaySources(FactBase):
    """
    The repositories roslab extracted into an underlay's ``src/``.

    Returns ``{"recorded": {path: sha256}, "present": [recorded paths whose folder exists]}``;
    empty when there is no underlay yet.
    """

    @staticmethod
    def default():
        return {"recorded": {}, "present": []}

    def command(self, underlay_dir: str) -> str:
        manifest = shlex.quote(posixpath.join(underlay_dir, MANIFEST))
        src = shlex.quote(posixpath.join(underlay_dir, "src"))
        # The paths in the manifest were checked when it was written; sed keeps only safe ones.
        return (f"[ -f {manifest} ] || exit 0; echo '## manifest'; cat {manifest}; echo; echo '## present'; "
                f"sed -n 's/^  \"\\([A-Za-z0-9_][A-Za-z0-9_.+/-]*\\)\": .*/\\1/p' {manifest} | "
                f"while read -r p; do [ -d {src}/\"$p\" ] && echo \"$p\"; done; true")

    def process(self, output):
        section, manifest, present = None, [], []
        for line in output:
            if line.startswith("## "):
                section = line[3:].strip()
            elif section == "manifest":
                manifest.append(line)
            elif section == "present" and line.strip():
                present.append(line.strip())
        try:
            recorded = json.loads("\n".join(manifest) or "{}")
        except ValueError:
            recorded = {}
        if not isinstance(recorded, dict):
            recorded = {}
        return {"recorded": {str(k): str(v) for k, v in recorded.items()}, "present": present}


def manifest_text(digests: dict[str, str]) -> str:
    """One `  "path": "sha256"` per line (the fact's sed reads the paths back)."""
    return json.dumps(dict(sorted(digests.items())), indent=2) + "\n"


def _as_user(user: str, script: str) -> StringCommand:
    return StringCommand(f"runuser -u {shlex.quote(user)} -- sh -c {shlex.quote(script)}")


@operation()
def sources(underlay_dir: str, repositories: list[dict], user: str):
    """
    Make an underlay's ``src/`` hold exactly these repositories, each as its archive has it.

    + underlay_dir: the underlay workspace on the host (absolute)
    + repositories: ``{"path", "sha256", "archive"}`` each (archive: the tar's bytes)
    + user: the login user, who owns the underlay (extraction runs as them)

    A repository is copied (its folder replaced whole) when its sha256 differs from the one
    recorded or its folder is gone; one recorded but no longer wanted is removed.
    """
    state = host.get_fact(UnderlaySources, underlay_dir=underlay_dir)
    recorded, present = state["recorded"], set(state["present"])
    wanted = {repo["path"]: repo for repo in repositories}
    _checked_paths(wanted)
    changed = sorted(path for path, repo in wanted.items()
                     if recorded.get(path) != repo["sha256"] or path not in present)
    removed = sorted(_checked_paths(path for path in recorded if path not in wanted
                                    and REPO_PATH.fullmatch(path) and ".." not in path.split("/")))
    digests = {path: repo["sha256"] for path, repo in wanted.items()}
    if not changed and not removed and recorded == digests:
        host.noop(f"{underlay_dir}/src holds {', '.join(sorted(wanted)) or 'no repositories'} at their pins")
        return
    ws = shlex.quote(underlay_dir)
    yield StringCommand("install", "-d", "-m", "755", ARCHIVE_DIR)
    for path in changed:
        repo = wanted[path]
        archive = f"{ARCHIVE_DIR}/{repo['sha256']}.tar"
        yield FileUploadCommand(io.BytesIO(repo["archive"]), archive,
                                remote_temp_filename=host.get_temp_filename(archive))
        target = shlex.quote(f"src/{path}")
        fresh = shlex.quote(f"src/{path}.roslab-new")
        yield _as_user(user, " && ".join([
            f"mkdir -p {ws}", f"cd {ws}", f"mkdir -p {shlex.quote(posixpath.dirname(f'src/{path}'))} "
            f"{shlex.quote(STATE_DIR_NAME)}",
            f"rm -rf {fresh}", f"mkdir {fresh}",
            f"tar -xf {shlex.quote(archive)} --no-same-owner -C {fresh}",
            f"rm -rf {target}", f"mv {fresh} {target}",
        ]))
        yield StringCommand("rm", "-f", shlex.quote(archive))
    for path in removed:
        yield _as_user(user, f"cd {ws} && rm -rf {shlex.quote(f'src/{path}')}")
    manifest = shlex.quote(MANIFEST)
    yield _as_user(user, f"mkdir -p {ws}/{shlex.quote(STATE_DIR_NAME)} && cd {ws} && "
                         f"printf '%s' {shlex.quote(manifest_text(digests))} > {manifest}.new && "
                         f"mv {manifest}.new {manifest}")


def colcon_meta(cmake_args: dict[str, list[str]], build_dependencies: dict[str, list[str]] | None = None) -> str:
    """colcon.meta text giving each package its CMake settings and the build-order edges its
    manifest lacks ("" when there are none)."""
    names: dict[str, dict] = {}
    for package, args in sorted(cmake_args.items()):
        if args:
            names.setdefault(package, {})["cmake-args"] = list(args)
    for package, needs in sorted((build_dependencies or {}).items()):
        if needs:
            # colcon-metadata adds these to every category (build, run, test) of the package
            names.setdefault(package, {})["dependencies"] = list(needs)
    return json.dumps({"names": names}, indent=2, sort_keys=True) + "\n" if names else ""


def build_stamp(digests: dict[str, str], distro: str, colcon_args: list[str],
                cmake_args: dict[str, list[str]] | None = None,
                build_dependencies: dict[str, list[str]] | None = None) -> str:
    """What a build is of: every repository's archive, the distro, colcon's arguments and the
    packages' CMake settings and extra build-order edges."""
    import hashlib

    text = "\0".join([*(f"{path}={sha}" for path, sha in sorted(digests.items())), distro, *colcon_args,
                      colcon_meta(cmake_args or {}, build_dependencies)])
    return hashlib.sha256(text.encode()).hexdigest()


def keep_in_use(slot: str) -> list[str]:
    """Shell lines moving the tree `install` points to aside (and `install` with it) when it is
    the one about to be made (`slot`, a shell word): a switch interrupted before its stamp."""
    return [f'if [ "$(readlink install 2>/dev/null)" = {slot} ]; then rm -rf {slot}.old && mv {slot} {slot}.old '
            f'&& ln -sfn {slot}.old install.roslab-new && mv -T install.roslab-new install; fi']


def slot_name(digest: str) -> str:
    """The install tree of a build: named for its inputs, the same on every host of a group."""
    return f"install-{digest[:12]}"


def build_script(underlay_dir: str, distro: str, colcon_args: list[str], stamp: str,
                 cmake_args: dict[str, list[str]] | None = None,
                 build_dependencies: dict[str, list[str]] | None = None,
                 slot: str | None = None, digest: str | None = None) -> str:
    """Build into the install tree `slot` (never the one in use); switch `install` to it only
    on success, and record that this host built it (`ORIGIN`)."""
    state_dir = STATE_DIR_NAME
    stamp_file = posixpath.join(state_dir, "build.sha256")
    slot = slot or slot_name(stamp)
    meta = colcon_meta(cmake_args or {}, build_dependencies)
    # colcon reads the packages' CMake settings only from a meta file it is pointed at
    metas = ["--metas", COLCON_META] if meta else []
    colcon = " ".join(shlex.quote(arg) for arg in ["colcon", "build", *colcon_args, *metas])
    progress = colcon_progress.build_lines(f'{colcon} --base-paths src --build-base "build-$slot" --install-base "$slot"',
                                           BUILD_LOG, "--base-paths src")
    write_meta = (f"printf '%s' {shlex.quote(meta)} > {COLCON_META}" if meta else f"rm -f {COLCON_META}")
    return "\n".join([
        f"cd {shlex.quote(underlay_dir)} || exit 1",
        f"mkdir -p log {state_dir}",
        f"rm -f {stamp_file}",  # no stamp while building: an interrupted build is tried again
        write_meta,
        f"slot={shlex.quote(slot)}",
        # the tree in use is never built into: an interrupted switch left `install` on it, so
        # the build goes beside it
        *keep_in_use("$slot"),
        'rm -rf "$slot" "build-$slot"',
        f"source /opt/ros/{shlex.quote(distro)}/setup.bash || exit 1",
        progress[0],  # how many packages: the run's "still running" line counts them (colcon_progress)
        f"if {progress[1]}; then",
        *(f"  {line}" for line in switch_script('"$slot"')),
        f"  {_write_stamp(stamp_file, stamp)}",
        f"  {_write_stamp(ORIGIN, origin_line(digest or stamp))}",
        "else",
        "  status=$?",
        f"  failed=$(sed -n 's/^Failed *<<< \\([^ ]*\\) .*/\\1/p' {BUILD_LOG} | head -n 1)",
        '  first=""',
        '  if [ -n "$failed" ]; then',
        # the line that says most: a tool's "error:" (compilers, setuptools, CMake), else a
        # Python exception's last line, else any line with an error word
        '    for f in log/latest_build/"$failed"/stderr.log log/latest_build/"$failed"/stdout_stderr.log; do',
        '      [ -f "$f" ] || continue',
        """      [ -z "$first" ] && first=$(grep -m 1 -E '(^|[^A-Za-z])(error|ERROR|fatal error):|CMake Error' "$f")""",
        """      [ -z "$first" ] && first=$(grep -E '^[A-Za-z_.]*(Error|Exception): ' "$f" | tail -n 1)""",
        """      [ -z "$first" ] && first=$(grep -m 1 -iE 'error|failed|not found' "$f")""",
        '    done',
        "  else",
        f'    first=$(grep -m 1 -iE "error" {BUILD_LOG})',
        "  fi",
        f"  tail -n 20 {BUILD_LOG} >&2",
        '  echo "roslab: underlay: package ${failed:-?} failed to build: ${first:-see '
        f'{posixpath.join(underlay_dir, BUILD_LOG)}}}; the last good install stays in use" >&2',
        "  exit $status",
        "fi",
    ])


@operation()
def built(underlay_dir: str, distro: str, colcon_args: list[str], stamp: str,
          cmake_args: dict[str, list[str]] | None = None,
          build_dependencies: dict[str, list[str]] | None = None,
          slot: str | None = None, digest: str | None = None):
    """
    Build an underlay (colcon) when its sources changed since the last successful build.

    + underlay_dir: the underlay on the host (absolute)
    + distro: ROS 2 distro whose ``/opt/ros/<distro>/setup.bash`` is sourced for the build
    + colcon_args: arguments after ``colcon build``
    + stamp: ``build_stamp(...)`` of what is to be built
    + cmake_args: CMake settings per package (``{package: ["-DNAME=value"]}``), written to
      ``.roslab/colcon.meta`` and given to colcon with ``--metas``
    + build_dependencies: build-order edges per package (``{package: [built before it]}``),
      in the same colcon.meta
    + slot: the install tree to build into (``slot_name(digest)``)
    + digest: the group's input digest (roslab.sources.groups), recorded as this host's build

    Run it as the underlay's owner (``_sudo_user``). A failed build leaves the last good
    install in use and fails with the package and its first error line.
    """
    stamps = host.get_fact(WorkspaceStamps, workspace_dir=underlay_dir)
    if stamps.get("build") == stamp and stamps.get("installed"):
        host.noop(f"{underlay_dir} is built from these sources already")
        return
    yield StringCommand("bash", "-c", shlex.quote(build_script(underlay_dir, distro, colcon_args, stamp,
                                                               cmake_args, build_dependencies, slot, digest)))
