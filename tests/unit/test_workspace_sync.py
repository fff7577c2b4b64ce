"""The workspace sync (roslab.ros.workspace.packages): nodes/ in, commands out.

Most tests run the operation against a "host" that is a temporary directory on this
machine: the fact's shell command runs locally and the commands the operation yields
are applied locally, so what is checked is what a student would find in ~/ros2_ws/src.
"""

from __future__ import annotations

import getpass
import grp
import os
import shutil
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from pyinfra.api import FileUploadCommand, StringCommand
from pyinfra.context import ctx_host, ctx_state

from roslab.ros import workspace

USER = getpass.getuser()
GROUP = grp.getgrgid(os.getgid()).gr_name


class LocalDirHost:
    """A stand-in for pyinfra's host whose facts run as shell commands on this machine."""

    name = "local"

    def __init__(self, facts: dict | None = None):
        self.facts = facts or {}
        self.noops: list[str] = []
        self.fact_calls: list[str] = []
        self.data = SimpleNamespace()

    def get_fact(self, cls, **kwargs):
        self.fact_calls.append(cls.__name__)
        if cls in self.facts:
            return self.facts[cls]
        fact = cls()
        command = fact.command(**kwargs)
        if isinstance(command, StringCommand):
            command = command.get_raw_value()
        result = subprocess.run(["sh", "-c", command], capture_output=True, text=True, check=True)
        return fact.process(result.stdout.splitlines())

    def noop(self, description):
        self.noops.append(description)

    def log(self, *args, **kwargs):
        pass

    def get_temp_filename(self, dest, temp_directory=None):
        return f"/tmp/pyinfra-{abs(hash(dest))}"


def run_operation(op, *args, host=None, diff=False, **kwargs):
    """Run an operation's generator with `host` in pyinfra's context; return its commands."""
    host = host or LocalDirHost()
    fake_state = SimpleNamespace(config=SimpleNamespace(DIFF=diff))
    with ctx_host.use(host), ctx_state.use(fake_state):
        return list(op._inner(*args, **kwargs)), host


def apply_locally(commands):
    for command in commands:
        if isinstance(command, FileUploadCommand):
            if hasattr(command.src, "read"):
                Path(command.dest).write_text(command.src.read())
            else:
                shutil.copyfile(command.src, command.dest)
        else:
            assert isinstance(command, StringCommand)
            subprocess.run(["sh", "-c", command.get_raw_value()], check=True)


def sync(nodes, src):
    commands, host = run_operation(
        workspace.packages, nodes_dir=str(nodes), src_dir=str(src), user=USER
    )
    apply_locally(commands)
    return commands, host


def uploads(commands):
    return sorted(
        os.path.basename(c.dest) for c in commands if isinstance(c, FileUploadCommand)
    )


def tree(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): p.read_text()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def make_package(nodes: Path, name: str, files: dict[str, str] | None = None) -> Path:
    package = nodes / name
    (package / "resource").mkdir(parents=True)
    (package / "package.xml").write_text(f"<package><name>{name}</name></package>\n")
    (package / "resource" / name).write_text("")
    for relative, text in (files or {}).items():
        (package / relative).parent.mkdir(parents=True, exist_ok=True)
        (package / relative).write_text(text)
    return package


@pytest.fixture
def nodes(tmp_path):
    nodes = tmp_path / "nodes"
    make_package(nodes, "demo", {"demo/talker.py": "print('hi')\n", "setup.py": "setup()\n"})
    make_package(nodes, "bringup", {"launch/main.launch.py": "# main\n"})
    return nodes


@pytest.fixture
def src(tmp_path):
    src = tmp_path / "ws" / "src"
    src.mkdir(parents=True)
    return src


def test_first_sync_copies_every_package_and_writes_the_manifest(nodes, src):
    commands, _ = sync(nodes, src)

    expected = {f"{p}": text for p, text in tree(nodes).items()}
    copied = tree(src)
    manifest = copied.pop(".roslab-manifest")
    assert copied == expected
    assert manifest.endswith("bringup\ndemo\n")
    assert manifest.startswith("# managed by roslab")


def test_second_sync_is_a_noop_that_says_why(nodes, src):
    sync(nodes, src)
    commands, host = sync(nodes, src)
    assert commands == []
    assert host.noops == [f"packages bringup, demo in {src} match {nodes}"]


def test_the_whole_tree_is_read_with_one_fact(nodes, src):
    _, host = sync(nodes, src)
    assert host.fact_calls == ["WorkspacePackages"]


def test_only_the_edited_file_is_uploaded(nodes, src):
    sync(nodes, src)
    (nodes / "demo" / "demo" / "talker.py").write_text("print('hello')\n")
    commands, _ = sync(nodes, src)
    assert uploads(commands) == ["talker.py"]
    assert (src / "demo" / "demo" / "talker.py").read_text() == "print('hello')\n"


def test_a_file_deleted_from_nodes_is_deleted_from_the_workspace(nodes, src):
    sync(nodes, src)
    (nodes / "demo" / "demo" / "talker.py").unlink()
    (nodes / "demo" / "demo").rmdir()
    commands, _ = sync(nodes, src)
    assert uploads(commands) == []
    assert not (src / "demo" / "demo").exists()
    assert (src / "demo" / "setup.py").exists()


def test_a_package_removed_from_nodes_goes_but_a_students_package_stays(nodes, src):
    student = src / "my_robot"
    student.mkdir()
    (student / "package.xml").write_text("<package/>\n")
    sync(nodes, src)
    shutil.rmtree(nodes / "bringup")

    commands, _ = sync(nodes, src)

    assert not (src / "bringup").exists()
    assert (student / "package.xml").read_text() == "<package/>\n"
    assert (src / ".roslab-manifest").read_text().endswith("\ndemo\n")


def test_a_students_extra_file_inside_a_managed_package_is_removed(nodes, src):
    sync(nodes, src)
    (src / "demo" / "notes.txt").write_text("scratch\n")
    (src / "demo" / "link").symlink_to("/etc/hostname")
    commands, _ = sync(nodes, src)
    assert uploads(commands) == []
    assert sorted(os.listdir(src / "demo")) == ["demo", "package.xml", "resource", "setup.py"]


def test_executable_bit_follows_nodes(nodes, src):
    sync(nodes, src)
    script = nodes / "demo" / "setup.py"
    script.chmod(0o755)
    commands, _ = sync(nodes, src)
    assert uploads(commands) == []  # content unchanged: only the mode is fixed
    assert oct((src / "demo" / "setup.py").stat().st_mode & 0o777) == "0o755"
    assert sync(nodes, src)[0] == []


def test_a_directory_where_a_file_belongs_is_replaced(nodes, src):
    sync(nodes, src)
    (src / "demo" / "setup.py").unlink()
    (src / "demo" / "setup.py").mkdir()
    (src / "demo" / "setup.py" / "junk").write_text("x")
    sync(nodes, src)
    assert (src / "demo" / "setup.py").read_text() == "setup()\n"


def test_caches_and_local_build_output_are_not_copied(nodes, src):
    (nodes / "demo" / "demo" / "__pycache__").mkdir()
    (nodes / "demo" / "demo" / "__pycache__" / "talker.cpython-311.pyc").write_bytes(b"\0")
    (nodes / "demo" / "build").mkdir()
    (nodes / "demo" / "build" / "x").write_text("x")
    sync(nodes, src)
    assert not (src / "demo" / "demo" / "__pycache__").exists()
    assert not (src / "demo" / "build").exists()


def test_files_owned_by_someone_else_are_given_back_to_the_user():
    local = {"demo": {"demo/package.xml": workspace.LocalFile("/x", "aa", "644")}}
    remote = {
        "manifest": ["demo"],
        "group": "ubuntu",
        "entries": {
            "demo": workspace.RemoteEntry("d", "755", "ubuntu", "ubuntu"),
            "demo/package.xml": workspace.RemoteEntry("f", "644", "root", "root", "aa"),
        },
    }
    plan = workspace.plan_sync(local, remote, "ubuntu")
    assert plan.chown_packages == ["demo"] and plan.upload == []


def test_nothing_to_do_when_host_matches():
    local = {"demo": {"demo/package.xml": workspace.LocalFile("/x", "aa", "644")}}
    remote = {
        "manifest": ["demo"],
        "group": "ubuntu",
        "entries": {
            "demo": workspace.RemoteEntry("d", "755", "ubuntu", "ubuntu"),
            "demo/package.xml": workspace.RemoteEntry("f", "644", "ubuntu", "ubuntu", "aa"),
        },
    }
    assert workspace.plan_sync(local, remote, "ubuntu").is_empty()


def test_fact_parses_names_with_spaces_and_escaped_names():
    fact = workspace.WorkspacePackages()
    parsed = fact.process(
        [
            "## group",
            "ubuntu",
            "## manifest",
            "# managed by roslab",
            "demo",
            "../etc",
            "## entries",
            "d 755 ubuntu ubuntu demo",
            "f 644 ubuntu ubuntu demo/a file.txt",
            "## sums",
            "ab12  demo/a file.txt",
        ]
    )
    assert parsed["manifest"] == ["demo"]  # never a path outside src/
    assert parsed["entries"]["demo/a file.txt"].sha256 == "ab12"
    assert workspace._parse_sha256sum_line("\\cd34  demo/back\\\\slash") == ("cd34", "demo/back\\slash")


def test_missing_src_dir_reads_as_empty(tmp_path, nodes):
    commands, host = run_operation(
        workspace.packages, nodes_dir=str(nodes), src_dir=str(tmp_path / "nope"), user=USER
    )
    assert uploads(commands)  # everything would be uploaded
    assert host.noops == []


def test_nodes_dir_without_packages_is_a_clear_error(tmp_path, src):
    (tmp_path / "empty").mkdir()
    with pytest.raises(Exception, match="holds no ROS packages"):
        run_operation(workspace.packages, nodes_dir=str(tmp_path / "empty"), src_dir=str(src), user=USER)


def test_diff_mode_shows_the_changed_lines(nodes, src, caplog):
    sync(nodes, src)
    (nodes / "demo" / "setup.py").write_text("setup(name='demo')\n")
    with caplog.at_level("INFO"):
        run_operation(
            workspace.packages, nodes_dir=str(nodes), src_dir=str(src), user=USER, diff=True,
            host=LocalDirHost(),
        )
    assert "setup(name='demo')" in caplog.text


def test_a_file_rewritten_in_the_same_instant_with_the_same_size_gets_its_new_digest(tmp_path):
    """The controller hashes a file once while it is unchanged (deploy.py runs once per host);
    an edit is always seen, even one that keeps the size and the modification time."""
    import hashlib

    from roslab.controller_files import file_sha256

    from roslab import controller_files

    path = tmp_path / "talker.py"
    path.write_text("print('a')\n")
    stamp = path.stat()
    assert file_sha256(path) == hashlib.sha256(b"print('a')\n").hexdigest()
    assert not [key for key in controller_files._DIGESTS if key[1] == stamp.st_ino]  # just written: not kept
    for _ in range(3):  # rewritten within the same clock tick, size and mtime kept
        path.write_text("print('b')\n")
        os.utime(path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
        assert file_sha256(path) == hashlib.sha256(b"print('b')\n").hexdigest()
        path.write_text("print('a')\n")
        os.utime(path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
        assert file_sha256(path) == hashlib.sha256(b"print('a')\n").hexdigest()

    settled = tmp_path / "listener.py"
    settled.write_text("print('c')\n")
    os.utime(settled, ns=(0, 0))
    time.sleep(1.5 * controller_files.RECENT_CHANGE_NS / 1e9)  # a file last changed a while ago is kept
    assert file_sha256(settled) == file_sha256(settled) == hashlib.sha256(b"print('c')\n").hexdigest()
    assert [key for key in controller_files._DIGESTS if key[1] == settled.stat().st_ino]
