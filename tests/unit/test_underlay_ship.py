"""A class compiles once (issue 31): the deploy plans one build per group and a receive on the
others; the controller's cache of builds (sha256-checked); the receive script on a real folder
(atomic, last good install kept); and a failed build named on its group's receivers."""

from __future__ import annotations

import base64
import hashlib
import os
import io
import subprocess
import tarfile
from pathlib import Path

import pytest
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from test_sources import deploy_data, underlay_facts, upstream_repo

from roslab.sources import fetch as source_fetch
from roslab.sources import underlay
from roslab.sources import ship as underlay_ship
from roslab.sources.groups import input_digest


@pytest.fixture(autouse=True)
def _fresh(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    source_fetch.reset()
    yield
    source_fetch.reset()


def run_sources_deploy():
    from deploy.sources import sources as sources_deploy

    sources_deploy()


def class_of(tmp_path, memory_mb=3796, **more):
    """One robot's data with a pinned repository, and the facts of a host without an underlay."""
    bare, _ = upstream_repo(tmp_path)
    data = deploy_data(tmp_path, bare, "v1", **more)
    ubuntu = FakeUbuntu()
    ubuntu.memory_mb = memory_mb
    return data, {**ubuntu.facts(), **underlay_facts()}


def texts(result) -> str:
    return "\n".join(line for op in result.operations for line in op.text())


def test_the_first_host_of_a_group_builds_and_the_next_receives_without_colcon(tmp_path):
    data, facts = class_of(tmp_path)
    first = plan(run_sources_deploy, facts, {**data, "roslab_hostname": "team1-robot"}, host_name="team1-robot",
                 hosts_after=(("team2-robot", data),))
    assert not first.failed, first.errors
    assert "colcon build" in texts(first)
    assert "call ensure_cached" not in texts(first)

    second = plan(run_sources_deploy, facts, data, host_name="team2-robot", other_hosts=(("team1-robot", data),))
    assert not second.failed, second.errors
    assert "colcon build" not in texts(second)
    receive = second.operation("holds the underlay built on team1-robot")
    steps = receive.text()
    assert steps[:2] == ["call ensure_cached", "call _write_ship_record"]
    assert any(step.startswith(f"upload {underlay.ARCHIVE_DIR}/underlay-") for step in steps)
    assert any("sha256sum -c" in step for step in steps)
    # rosdep's dependencies are still installed on the receiving host
    assert "rosdep install --from-paths src/lidar" in texts(second)


def test_another_architecture_is_another_group_with_its_own_build(tmp_path, monkeypatch):
    import pyinfra.api.host as pyinfra_host
    from pyinfra.facts.server import Arch

    data, facts = class_of(tmp_path)
    machines = {"team1-robot": "x86_64", "team2-robot": "aarch64"}

    def deploy():
        fake = pyinfra_host.get_fact  # the test host's facts, for every host

        def by_host(state, host, cls, args=None, kwargs=None, **more):
            if cls is Arch:
                return machines[host.name]
            return fake(state, host, cls, args, kwargs, **more)

        monkeypatch.setattr(pyinfra_host, "get_fact", by_host)
        run_sources_deploy()

    result = plan(deploy, facts, data, host_name="team2-robot", other_hosts=(("team1-robot", data),))
    assert not result.failed, result.errors
    assert "colcon build" in texts(result)
    assert "call ensure_cached" not in texts(result)


def test_a_reimaged_builder_receives_the_tree_a_teammate_holds_instead_of_compiling(tmp_path, monkeypatch):
    """The controller's cache is gone and team1-robot (the group's first host) was re-imaged;
    team2-robot holds the same build: it is the source, and nothing is compiled."""
    import pyinfra.api.host as pyinfra_host

    from roslab.ros.workspace import WorkspaceStamps

    data, facts = class_of(tmp_path)
    stamps = []
    monkeypatch.setattr(underlay, "build_stamp", lambda *args, real=underlay.build_stamp: stamps.append(
        real(*args)) or stamps[-1])

    def deploy():
        fake = pyinfra_host.get_fact  # the test host's facts (an empty underlay), for every host

        def by_host(state, host, cls, args=None, kwargs=None, **more):
            if cls is WorkspaceStamps and host.name == "team2-robot":
                return {"rosdep": None, "build": stamps[-1], "installed": True}
            return fake(state, host, cls, args, kwargs, **more)

        monkeypatch.setattr(pyinfra_host, "get_fact", by_host)
        run_sources_deploy()

    result = plan(deploy, facts, data, host_name="team1-robot", hosts_after=(("team2-robot", data),))
    assert not result.failed, result.errors
    assert "colcon build" not in texts(result)
    result.operation("holds the underlay built on team2-robot")


def test_a_host_under_the_profiles_memory_never_builds_it_receives(tmp_path):
    data, facts = class_of(tmp_path, memory_mb=906)
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import resolve_host

    base, _ = resolve_host(builtin_profiles()["demo"], {}, distro="jazzy", role="robot")  # every key host_settings reads
    profile = {**(data.get("roslab_profile") or base), "name": "esp32_microros", "underlay_build_memory_mb": 1536}
    data = {**data, "roslab_profile": profile}
    # the same (fake) facts serve every host: all of them are small, so no host may build
    result = plan(run_sources_deploy, facts, data, host_name="team1-robot", hosts_after=(("team2-robot", data),))
    assert result.failed
    assert result.operations == []
    (line,) = [error for error in result.errors if "underlay" in error]
    assert "no host of this group has the 1536 MiB profile 'esp32_microros' asks for" in line
    assert "underlay_builder" in line and "nothing was changed on it" in line


def test_a_named_builder_builds_for_the_first_host_too(tmp_path):
    data, facts = class_of(tmp_path, underlay_builder="team2-robot")
    result = plan(run_sources_deploy, facts, data, host_name="team1-robot", hosts_after=(("team2-robot", data),))
    assert not result.failed, result.errors
    assert "colcon build" not in texts(result)
    result.operation("holds the underlay built on team2-robot")


def digest_of(data, tmp_path) -> str:
    entry = data["roslab_sources"][0]
    archive = source_fetch.fetched(entry, tmp_path / "sources-cache")
    stamp = underlay.build_stamp({"lidar": archive.sha256}, "jazzy", ["--executor", "sequential"])
    return input_digest(stamp, "aarch64", "/home/student/roslab_underlay")


def packed(files: dict[str, bytes]) -> bytes:
    stream = io.BytesIO()
    with tarfile.open(fileobj=stream, mode="w:gz") as tar:
        for name, body in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(body)
            tar.addfile(info, io.BytesIO(body))
    return stream.getvalue()


def test_a_cached_build_is_received_by_every_host_even_the_first_and_no_peer_is_asked(tmp_path):
    data, facts = class_of(tmp_path)
    digest = digest_of(data, tmp_path)
    body = packed({"./setup.sh": b"# colcon\n"})
    underlay_ship.store(tmp_path / "sources-cache", digest, "team9-robot", f"install-{digest[:12]}",
                        hashlib.sha256(body).hexdigest(), body)
    result = plan(run_sources_deploy, facts, data, host_name="team1-robot", hosts_after=(("team2-robot", data),))
    assert not result.failed, result.errors
    assert "colcon build" not in texts(result)
    result.operation("holds the underlay built on team9-robot")
    assert "MemoryTotal" not in result.facts_asked


def test_the_cache_keeps_a_build_only_with_its_sha256(tmp_path):
    digest = "ab" * 32
    body = packed({"./setup.sh": b"# colcon\n"})
    meta = underlay_ship.store(tmp_path, digest, "team1-robot", "install-abababababab",
                               hashlib.sha256(body).hexdigest(), body)
    assert underlay_ship.cached(tmp_path, digest) == meta
    tar, _ = underlay_ship.cache_paths(tmp_path, digest)
    tar.write_bytes(body[:-1] + b"x")  # damaged on the controller's disk
    assert underlay_ship.cached(tmp_path, digest) is None
    with pytest.raises(ValueError):
        underlay_ship.cache_paths(tmp_path, "../../etc")


def test_a_packed_build_is_taken_only_whole_and_matching_its_sha256():
    body = packed({"./setup.sh": b"# colcon\n"})
    sha = hashlib.sha256(body).hexdigest()
    lines = ["slot install-0123456789ab", f"sha256 {sha}", "## data",
             *base64.encodebytes(body).decode().splitlines()]
    assert underlay_ship.parse_pack(lines) == ("install-0123456789ab", sha, body)
    with pytest.raises(underlay_ship.ShipError, match="sha256 differs"):
        underlay_ship.parse_pack(lines[:3] + base64.encodebytes(body[:-3]).decode().splitlines())
    with pytest.raises(underlay_ship.ShipError, match="incomplete"):
        underlay_ship.parse_pack(lines[:2])
    with pytest.raises(underlay_ship.ShipError, match="incomplete"):
        underlay_ship.parse_pack(["slot ../../etc", *lines[1:]])


class FailedBuild:
    """A builder's build operation as pyinfra leaves it after colcon failed."""

    _hash = "build"
    stderr_lines = ["Summary: 1 package failed", "roslab: underlay: package micro_ros_agent failed to build: "
                    "error: 'uxr' was not declared; the last good install stays in use"]

    def is_complete(self):
        return True

    def did_succeed(self):
        return False


def test_a_failed_build_fails_its_receivers_naming_the_builder_and_the_package(tmp_path):
    from pyinfra.api import Config, Inventory, State

    inventory = Inventory(([("team1-robot", {}), ("team2-robot", {})], {}))
    state = State(inventory, Config())
    digest = "cd" * 32
    underlay_ship.note_build(state, digest, "team1-robot", FailedBuild())
    said = []
    receiver = inventory.get_host("team2-robot")
    receiver.log_styled = lambda text, **_: said.append(text)
    assert underlay_ship.ensure_cached(state, receiver, digest, "team1-robot", str(tmp_path), "/u", "s") is False
    assert said == ["roslab: underlay: its group's builder team1-robot failed to build it: package micro_ros_agent "
                    "failed to build: error: 'uxr' was not declared; this host receives its underlay from there"]
    # a builder stopped before its build: named too
    said.clear()
    assert underlay_ship.ensure_cached(state, receiver, "ef" * 32, "team1-robot", str(tmp_path), "/u", "s") is False
    assert "builder team1-robot did not build it in this run" in said[0]


def test_a_builder_lost_mid_build_is_named_lost_not_failed_by_its_receivers(tmp_path, monkeypatch):
    from pyinfra.api import Config, Inventory, State

    inventory = Inventory(([("team1-robot", {}), ("team2-robot", {})], {}))
    state = State(inventory, Config())
    digest = "cd" * 32
    underlay_ship.note_build(state, digest, "team1-robot", FailedBuild())
    builder = inventory.get_host("team1-robot")
    state.failed_hosts.add(builder)
    monkeypatch.setattr(underlay_ship, "builder_lost", lambda source: source is builder)
    said = []
    receiver = inventory.get_host("team2-robot")
    receiver.log_styled = lambda text, **_: said.append(text)
    assert underlay_ship.ensure_cached(state, receiver, digest, "team1-robot", str(tmp_path), "/u", "s") is False
    (line,) = said
    assert line.startswith("roslab: underlay: its group's builder team1-robot was lost before it finished building "
                           "it (it stopped answering: powered off"), line
    assert "failed to build" not in line and "run again once the builder answers" in line


def test_a_full_disk_is_one_line_naming_the_underlays_folder_not_tars_first_complaint(tmp_path):
    ws = tmp_path / "roslab_underlay"
    (ws / "install-a").mkdir(parents=True)
    (ws / "install").symlink_to("install-a")
    stubs = tmp_path / "bin"  # a stand-in for tar on a full disk: its complaints, exit 2
    stubs.mkdir()
    (stubs / "tar").write_text("#!/bin/sh\necho 'tar: ./lib/libx.so: Cannot write: No space left on device' >&2\n"
                               "echo 'tar: Exiting with failure status due to previous errors' >&2\nexit 2\n")
    (stubs / "tar").chmod(0o755)
    tar, record = tmp_path / "shipped.tar.gz", tmp_path / "shipped.ship"
    tar.write_bytes(b"")
    record.write_text("slot=install-0123456789ab\n")
    script = underlay_ship.receive_script(str(ws), str(tar), str(record), "stamp-2", "12" * 32, "team1-robot")
    done = subprocess.run(["sh", "-c", script], capture_output=True, text=True,
                          env={**os.environ, "PATH": f"{stubs}:{os.environ['PATH']}"})
    assert done.returncode == 1
    (line,) = done.stderr.splitlines()
    assert line.startswith(f"roslab: underlay: the disk holding {ws} is full (the build shipped from team1-robot "
                           "did not fit; "), line
    assert line.endswith(" free there): free space there and run again; the last good install stays in use")
    assert (ws / "install").readlink() == Path("install-a") and not list(ws.glob("*.roslab-new"))


# --- the receive script, on a real folder ---------------------------------------------------


def receive(ws: Path, tmp_path: Path, files: dict[str, bytes], slot: str, stamp="stamp-2", digest="12" * 32):
    tar = tmp_path / "shipped.tar.gz"
    tar.write_bytes(packed(files))
    record = tmp_path / "shipped.ship"
    record.write_text(f"slot={slot}\nsha256={hashlib.sha256(tar.read_bytes()).hexdigest()}\n")
    script = underlay_ship.receive_script(str(ws), str(tar), str(record), stamp, digest, "team1-robot")
    return subprocess.run(["sh", "-c", script], capture_output=True, text=True)


def test_the_shipped_tree_lands_in_the_builders_install_path_and_replaces_the_last_one(tmp_path):
    ws = tmp_path / "roslab_underlay"
    (ws / "install-a").mkdir(parents=True)
    (ws / "install-a" / "setup.sh").write_text("# old\n")
    (ws / "build-install-a").mkdir()
    (ws / "install").symlink_to("install-a")
    done = receive(ws, tmp_path, {"./setup.sh": b"# new\n"}, "install-0123456789ab")
    assert done.returncode == 0, done.stderr
    assert (ws / "install").readlink() == Path("install-0123456789ab")
    assert (ws / "install" / "setup.sh").read_text() == "# new\n"
    assert sorted(p.name for p in ws.iterdir()) == [".roslab", "install", "install-0123456789ab"]
    assert (ws / ".roslab" / "build.sha256").read_text() == "stamp-2\n"
    assert (ws / underlay.ORIGIN).read_text() == f"shipped from team1-robot {'12' * 32}\n"


def test_a_shipped_tree_that_does_not_extract_keeps_the_last_good_install(tmp_path):
    ws = tmp_path / "roslab_underlay"
    (ws / "install-a").mkdir(parents=True)
    (ws / "install").symlink_to("install-a")
    (ws / ".roslab").mkdir()
    (ws / ".roslab" / "build.sha256").write_text("stamp-1\n")
    tar = tmp_path / "shipped.tar.gz"
    tar.write_bytes(b"not a tar")
    record = tmp_path / "shipped.ship"
    record.write_text("slot=install-0123456789ab\nsha256=" + "0" * 64 + "\n")
    script = underlay_ship.receive_script(str(ws), str(tar), str(record), "stamp-2", "12" * 32, "team1-robot")
    done = subprocess.run(["sh", "-c", script], capture_output=True, text=True)
    assert done.returncode != 0
    assert "roslab: underlay: the build shipped from team1-robot does not extract into " in done.stderr
    assert done.stderr.count("\n") == 1 and str(ws) in done.stderr  # one line, naming the folder
    assert (ws / "install").readlink() == Path("install-a")
    assert not (ws / ".roslab" / "build.sha256").exists()  # the next run tries again
    assert not list(ws.glob("*.roslab-new"))


def test_a_record_naming_another_folder_is_refused(tmp_path):
    ws = tmp_path / "roslab_underlay"
    ws.mkdir()
    done = receive(ws, tmp_path, {"./setup.sh": b"x"}, "../../home")
    assert done.returncode != 0 and "names no install folder" in done.stderr
    assert not (ws / "install").exists()


def test_a_build_goes_into_the_groups_install_path_records_built_here_and_removes_the_old_tree(tmp_path):
    """The build script itself, with a fake colcon that installs into --install-base."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "colcon").write_text("#!/bin/sh\n"
                                    'while [ $# -gt 0 ]; do [ "$1" = --install-base ] && base=$2; shift; done\n'
                                    'mkdir -p "$base" && echo "# built" > "$base/setup.sh"\n')
    (bin_dir / "colcon").chmod(0o755)
    ros = tmp_path / "opt/ros/jazzy"
    ros.mkdir(parents=True)
    (ros / "setup.bash").write_text("true\n")
    ws = tmp_path / "ws"
    (ws / "install-a").mkdir(parents=True)
    (ws / "build-install-a").mkdir()
    (ws / "install").symlink_to("install-a")
    digest = "34" * 32
    script = underlay.build_script(str(ws), "jazzy", [], "stamp", slot=underlay.slot_name(digest), digest=digest)
    done = subprocess.run(["bash", "-c", script.replace("/opt/ros/", f"{tmp_path}/opt/ros/")],
                          capture_output=True, text=True, env={"PATH": f"{bin_dir}:/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    assert (ws / "install").readlink() == Path(f"install-{digest[:12]}")
    assert (ws / "install" / "setup.sh").read_text() == "# built\n"
    assert not (ws / "install-a").exists() and not (ws / "build-install-a").exists()
    assert (ws / underlay.ORIGIN).read_text() == f"built here {digest}\n"
    assert (ws / ".roslab/build.sha256").read_text() == "stamp\n"


def test_status_shows_where_each_hosts_underlay_came_from():
    from fixtures.classroom import typed
    from roslab.cli import status

    digest = "56" * 32
    script = status.probe_script(underlay=status.origin_file(typed(
        {"ssh_user": "ubuntu", "login_user": "student", "sources_underlay_dir": "~/roslab_underlay",
         "roslab_sources": [{"path": "a", "url": "https://x.org/a.git", "version": "v1"}]})))
    assert "head -c 200 ~student/roslab_underlay/.roslab/underlay-origin" in script
    assert status.origin_file(typed({"ssh_user": "ubuntu", "roslab_sources": []})) == ""

    def cell(lines, underlay="~student/x"):
        probe = status.parse_probe(["## underlay", *lines, "## end"])
        host = status.HostStatus(name="r", team="t", role="robot", address="a", reachable=True, probe=probe,
                                 underlay=underlay)
        return status.underlay_cell(host, True).text

    assert cell([f"shipped from team1-robot {digest}"]) == "shipped from team1-robot 565656565656"
    assert cell([f"built here {digest}"]) == "built here 565656565656"
    assert cell([]) == "none yet"
    assert cell(["shipped from $(reboot) x"]) == "none yet"  # a record roslab did not write
    assert cell([], underlay="") == "-"


def test_the_cache_keeps_the_newest_builds_of_a_group_and_any_a_host_of_the_run_needs(tmp_path):
    digests = [f"{index:x}" * 64 for index in range(1, 6)]  # oldest first
    for age, digest in enumerate(reversed(digests)):
        underlay_ship.store(tmp_path, digest, "team1-robot", "install-a", "0" * 64, b"tree", group="osr-jazzy")
        record = underlay_ship.cache_paths(tmp_path, digest)[1]
        os.utime(record, ns=(10**18 - age * 10**9, 10**18 - age * 10**9))
        underlay_ship.ship_record(tmp_path, digest).write_text("slot=install-a\n")
    other, older = "a" * 64, "b" * 64  # another group's, and one kept before groups were recorded
    underlay_ship.store(tmp_path, other, "team2-robot", "install-b", "0" * 64, b"tree", group="esp32-jazzy")
    underlay_ship.store(tmp_path, older, "team2-robot", "install-b", "0" * 64, b"tree")

    removed = underlay_ship.pruned(tmp_path, "osr-jazzy", in_use={digests[0]})

    assert removed == [digests[1]]  # the newest three kept, the oldest kept for a host that needs it
    left = {path.name.split(".")[0] for path in (tmp_path / underlay_ship.CACHE_FOLDER).iterdir()}
    assert left == {digests[0], *digests[2:], other, older}
