"""The classroom's apt cache: the cache host's apt-cacher-ng, every host's proxy script and
its fallback, the roster check; and rosdep's data downloaded once by the controller."""

from __future__ import annotations

import hashlib
import io
import socket
import subprocess
import tarfile
import textwrap

import pytest
import yaml
from pyinfra.facts.server import Command
from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy import apt_cache
from deploy.apt_cache import (
    DETECT_SCRIPT,
    PROXY_CONFIG,
    SERVER_CONFIG,
    apt_cache_client,
    apt_cache_filled,
    apt_cache_server,
    proxy_url,
)
from deploy.apt_ready import apt_lists
from deploy.rosdep import ARCHIVE, rosdep
from roslab import downloads
from roslab.ros import rosdep_data
from roslab.roster import RosterError, load_roster
from roslab.templating import render

CACHE = {"apt_cache_host": "team1-main"}


def client_facts(cache_answers: bool = True) -> dict:
    # The cache host is not in this test's run, so the client asks whether it answers.
    return {**FakeUbuntu().facts(), Command: lambda command: "up" if cache_answers else "down"}


def client_files(tmp_path, **settings) -> dict[str, str]:
    return plan(apt_cache_client, client_facts(), host_data(tmp_path, role="robot", **settings)).uploads()


def test_a_cache_that_does_not_answer_is_reported_in_one_line_naming_it(tmp_path, caplog):
    apt_cache._warned.clear()  # once per run: this test is a run of its own
    with caplog.at_level("WARNING"):
        result = plan(apt_cache_client, client_facts(cache_answers=False),
                      host_data(tmp_path, role="robot", **CACHE))
    assert not result.failed
    said = [record.getMessage() for record in caplog.records if "apt cache" in record.getMessage()]
    assert said == ["roslab: the apt cache on team1-main (10.11.0.2:3142) does not answer: "
                    "hosts download from upstream directly this run"]


def test_every_host_asks_the_cache_through_the_managed_script_for_http_only(tmp_path):
    files = client_files(tmp_path, **CACHE)
    config = [line for line in files[PROXY_CONFIG].splitlines() if line and not line.startswith("//")]
    # https sources are left alone: apt reads Acquire::https::Proxy-Auto-Detect for them.
    # No pipelining through the cache: apt-cacher-ng's early closes made apt lose a request.
    assert config == [f'Acquire::http::Proxy-Auto-Detect "{DETECT_SCRIPT}";',
                      'Acquire::http::Pipeline-Depth "0";']
    assert files[PROXY_CONFIG].startswith("// managed by roslab")
    assert "address=10.11.0.2\nport=3142\nproxy=http://10.11.0.2:3142/\n" in files[DETECT_SCRIPT]


def run_script(text: str, tmp_path) -> str:
    script = tmp_path / "apt-proxy-detect"
    script.write_text(text)
    script.chmod(0o755)
    return subprocess.run([str(script), "http://10.11.0.1/ubuntu"], capture_output=True, text=True,
                          timeout=10, check=True).stdout.strip()


def detect_script(port: int, offline: bool = False) -> str:
    return render("apt-proxy-detect.sh.j2", cache_host="team1-main", address="127.0.0.1", port=str(port),
                  proxy=proxy_url("127.0.0.1", port), timeout=1, offline=offline)


def test_the_script_names_the_cache_while_it_answers_and_says_direct_when_it_does_not(tmp_path):
    with socket.socket() as listening:  # loopback only
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        port = listening.getsockname()[1]
        assert run_script(detect_script(port), tmp_path) == f"http://127.0.0.1:{port}/"
    # The port is closed now: apt downloads from the source itself.
    assert run_script(detect_script(port), tmp_path) == "DIRECT"


def test_offline_never_falls_back_to_upstream(tmp_path):
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    assert run_script(detect_script(port, offline=True), tmp_path) == f"http://127.0.0.1:{port}/"


def test_a_roster_without_a_cache_host_removes_the_proxy_and_a_second_run_changes_nothing(tmp_path):
    host = FakeUbuntu()
    host.files[PROXY_CONFIG] = ["// managed by roslab"]
    first = plan(apt_cache_client, host.facts(), host_data(tmp_path))
    assert first.operation("uses no classroom apt cache").text() == [f"rm -f {PROXY_CONFIG}"]
    del host.files[PROXY_CONFIG]  # what `rm -f` does (FakeUbuntu.apply runs no shell)
    assert plan(apt_cache_client, host.facts(), host_data(tmp_path)).operations == []


def test_the_cache_host_installs_apt_cacher_ng_before_anything_else_and_only_it(tmp_path):
    host = FakeUbuntu()
    data = host_data(tmp_path, role="main", **CACHE)
    result = plan(apt_cache_server, host.facts(), data)
    names = [op.name.split(" | ")[1] for op in result.operations if op.commands]
    assert names[:3] == [
        "Ensure the Ubuntu apt sources enable universe (the apt cache's package is there)",
        "Ensure the apt lists are fresh before apt-cacher-ng is installed",
        "Ensure apt-cacher-ng is installed",
    ]
    config = result.uploads()[SERVER_CONFIG]
    assert "\nPort: 3142\n" in config and "\nAllowUserPorts: 80\n" in config and "\nOfflinemode: 0\n" in config
    robot = host_data(tmp_path, role="robot", **CACHE)
    assert plan(apt_cache_server, FakeUbuntu().facts(), robot).operations == []


def test_offline_and_a_mirrors_port_reach_the_cache_configuration(tmp_path):
    data = host_data(tmp_path, role="main", offline=True, apt_cache_upstream_ports=[80, 8080], **CACHE)
    config = plan(apt_cache_server, FakeUbuntu().facts(), data).uploads()[SERVER_CONFIG]
    assert "\nAllowUserPorts: 80 8080\n" in config and "\nOfflinemode: 1\n" in config


def class_of(tmp_path, **settings) -> dict[str, dict]:
    """A class on one cache: team1 and team2 on Ubuntu 24.04, team3-main on 22.04."""
    hosts = {}
    for team, role, codename in (("team1", "main", "noble"), ("team1", "robot", "noble"),
                                 ("team2", "main", "noble"), ("team3", "main", "jammy")):
        data = host_data(tmp_path, codename=codename, role=role, **CACHE, **settings)
        data.update(roslab_team=team, roslab_hostname=f"{team}-{role}")
        hosts[f"{team}-{role}"] = data
    return hosts


def fill_plan(tmp_path, name: str, host: FakeUbuntu | None = None, deploy=apt_cache_filled, **settings):
    """apt_cache_filled planned on `name`, the whole class in the run, in roster order."""
    hosts = class_of(tmp_path, **settings)
    names = list(hosts)
    at = names.index(name)
    before = tuple((other, hosts[other]) for other in names[:at])
    after = tuple((other, hosts[other]) for other in names[at + 1:])
    host = host or FakeUbuntu(codename="jammy" if name.startswith("team3") else "noble")
    return plan(deploy, host.facts(), hosts[name], host_name=name, other_hosts=before,
                hosts_after=after)


def test_the_first_host_of_each_release_fills_the_cache_for_its_release_one_at_a_time(tmp_path):
    first = fill_plan(tmp_path, "team1-main")
    (download,) = first.operations
    assert download.arguments["_serial"] is True  # the releases share arch:all .debs
    (command,) = download.text()
    assert "apt-get -y" in command and "install --download-only -- " in command
    # Every role's packages of the release: the robots' ros-base too, not only its own desktop.
    assert command.endswith("-- locales openssh-server ros-dev-tools ros-jazzy-desktop ros-jazzy-ros-base")
    assert fill_plan(tmp_path, "team1-robot").operations == []
    assert fill_plan(tmp_path, "team2-main").operations == []
    # The first (only) 22.04 host fills for its release, with its distro's packages.
    (jammy,) = fill_plan(tmp_path, "team3-main").operations
    assert jammy.text()[0].endswith("-- locales openssh-server ros-dev-tools ros-humble-desktop")


def test_the_first_host_of_each_release_updates_its_lists_before_the_class(tmp_path):
    # Twelve hosts refreshing the same new index through apt-cacher-ng at once made it fail
    # some of them; updated first, the cache answers the others from fresh copies.
    (first,) = fill_plan(tmp_path, "team1-main", deploy=apt_lists).operations
    assert "before the other hosts" in first.name and first.arguments["_serial"] is True
    (robot,) = fill_plan(tmp_path, "team1-robot", deploy=apt_lists).operations
    # The others follow one at a time: apt-cacher-ng failed one of several hosts refreshing the
    # same index in the same second, and that host's apt-get update never ended.
    assert "one host at a time" in robot.name and robot.arguments["_serial"] is True
    assert first.text() == robot.text()  # the same update, only its turn differs


def test_a_filled_host_downloads_nothing_again_and_says_why(tmp_path):
    host = FakeUbuntu()
    host.packages.update({name: ["1"] for name in
                          ("locales", "openssh-server", "ros-dev-tools", "ros-jazzy-desktop")})
    result = fill_plan(tmp_path, "team1-main", host)
    assert result.changing() == {}
    assert result.noops == ["the packages are installed here: the run that installed them filled the cache"]


def test_nothing_is_filled_without_a_cache_or_while_the_cache_host_is_not_in_the_run(tmp_path):
    no_cache = host_data(tmp_path, role="main")
    assert plan(apt_cache_filled, FakeUbuntu().facts(), no_cache).operations == []
    # Only team1-robot is in this run (e.g. --limit): its cache host is not converged first.
    robot = class_of(tmp_path)["team1-robot"]
    assert plan(apt_cache_filled, FakeUbuntu().facts(), robot, host_name="team1-robot").operations == []
    switched_off = fill_plan(tmp_path, "team1-main", apt_cache_enabled=False)
    assert switched_off.operations == []


def test_a_cache_host_that_is_not_in_the_roster_is_refused_before_any_host_is_touched(tmp_path):
    roster = tmp_path / "classroom.yaml"
    roster.write_text(textwrap.dedent("""\
        classroom:
          apt_cache_host: team1-mian
        teams:
          team1:
            hosts:
              team1-main: {role: main, address: 10.0.0.2}
        """))
    with pytest.raises(RosterError) as error:
        load_roster(roster)
    assert ("classroom.yaml:2: field 'apt_cache_host': 'team1-mian' is not a host of this roster "
            "(did you mean 'team1-main'?)") in str(error.value)


# --- rosdep's data, downloaded once by the controller ------------------------------------

SOURCES_LIST = "# generic\nyaml base.yaml\nyaml https://example.invalid/rules/python.yaml\n" \
               "gbpdistro releases/fuerte.yaml fuerte\nnonsense line\n"
INDEX = {"type": "index", "version": 4, "distributions": {
    "jazzy": {"distribution": ["jazzy/distribution.yaml"], "distribution_cache": "jazzy-cache.yaml.gz",
              "distribution_status": "active", "distribution_type": "ros2", "python_version": 3},
    "humble": {"distribution": ["humble/distribution.yaml"], "distribution_status": "active"},
}}


def test_the_sources_list_points_at_local_copies_and_keeps_tags():
    text, wanted = rosdep_data.local_sources_list(SOURCES_LIST, "https://example.invalid/rosdep/20-default.list")
    lines = [line for line in text.splitlines() if not line.startswith("#")]
    assert lines == [
        f"yaml file://{rosdep_data.HOST_DIR}/sources/01-base.yaml",
        f"yaml file://{rosdep_data.HOST_DIR}/sources/02-python.yaml",
        f"gbpdistro file://{rosdep_data.HOST_DIR}/sources/03-fuerte.yaml fuerte",
    ]
    assert wanted == {
        "sources/01-base.yaml": "https://example.invalid/rosdep/base.yaml",
        "sources/02-python.yaml": "https://example.invalid/rules/python.yaml",
        "sources/03-fuerte.yaml": "https://example.invalid/rosdep/releases/fuerte.yaml",
    }


def test_the_index_lists_the_hosts_distro_only_with_its_files_and_cache_local():
    text, wanted = rosdep_data.local_index(yaml.safe_dump(INDEX), "https://example.invalid/index-v4.yaml", "jazzy")
    index = yaml.safe_load(text)
    assert list(index["distributions"]) == ["jazzy"]
    jazzy = index["distributions"]["jazzy"]
    assert jazzy["distribution"] == [f"file://{rosdep_data.HOST_DIR}/rosdistro/jazzy/01-distribution.yaml"]
    assert jazzy["distribution_cache"] == f"file://{rosdep_data.HOST_DIR}/rosdistro/jazzy/00-jazzy-cache.yaml.gz"
    assert sorted(wanted.values()) == ["https://example.invalid/jazzy-cache.yaml.gz",
                                       "https://example.invalid/jazzy/distribution.yaml"]
    with pytest.raises(rosdep_data.RosdepDataError, match="has no distro 'kilted'"):
        rosdep_data.local_index(yaml.safe_dump(INDEX), "https://example.invalid/index-v4.yaml", "kilted")


def serve_files(tmp_path) -> tuple[str, str]:
    """rosdep's data as file:// URLs (the controller fetches them like any URL)."""
    root = tmp_path / "upstream"
    (root / "jazzy").mkdir(parents=True)
    (root / "20-default.list").write_text("yaml base.yaml\n")
    (root / "base.yaml").write_text("git: {ubuntu: [git]}\n")
    # Absolute: the test below serves the index itself from an http:// URL, never fetched.
    index = {"type": "index", "version": 4,
             "distributions": {"jazzy": {"distribution": [f"file://{root}/jazzy/distribution.yaml"]}}}
    (root / "index-v4.yaml").write_text(yaml.safe_dump(index))
    (root / "jazzy/distribution.yaml").write_text("type: distribution\nversion: 2\n")
    return f"file://{root}/20-default.list", f"file://{root}/index-v4.yaml"


@pytest.fixture
def fresh_downloads():
    downloads._fetched.clear()
    rosdep_data._built.clear()
    yield
    downloads._fetched.clear()
    rosdep_data._built.clear()


def test_the_data_is_one_deterministic_archive_and_offline_uses_the_kept_copies(tmp_path, fresh_downloads):
    sources, index = serve_files(tmp_path)
    cache = tmp_path / "cache"
    online = rosdep_data.for_distro(sources, index, "jazzy", cache)
    assert online.files == ("rosdistro/index.yaml", "rosdistro/jazzy/01-distribution.yaml", "sources/01-base.yaml")
    with tarfile.open(fileobj=io.BytesIO(online.archive)) as archive:
        assert archive.extractfile("sources/01-base.yaml").read() == b"git: {ubuntu: [git]}\n"
        assert {member.mtime for member in archive.getmembers()} == {0}
    assert online.index_url == f"file://{rosdep_data.HOST_DIR}/rosdistro/index.yaml"

    (tmp_path / "upstream").rename(tmp_path / "gone")  # no internet now
    downloads._fetched.clear()
    rosdep_data._built.clear()
    offline = rosdep_data.for_distro(sources, index, "jazzy", cache, offline=True)
    assert offline.archive == online.archive and offline.sources_list == online.sources_list
    with pytest.raises(rosdep_data.RosdepDataError, match="offline, and .* is not in the controller's cache"):
        rosdep_data.for_distro(sources, index, "jazzy", tmp_path / "empty-cache", offline=True)


def test_hosts_get_the_archive_and_a_second_run_changes_nothing(tmp_path, fresh_downloads):
    sources, index = serve_files(tmp_path)
    host = FakeUbuntu()
    host.commands_on_path.add("rosdep")
    data = host_data(tmp_path, rosdep_data_from_controller=True, rosdep_sources_list_url=sources,
                     rosdistro_index_url="http://10.11.0.1/index-v4.yaml", rosdep_cache_dir=str(tmp_path / "c"))
    # The index URL is http:// (the schema's format); serve it from the file.
    downloads._fetched["http://10.11.0.1/index-v4.yaml"] = (tmp_path / "upstream/index-v4.yaml").read_bytes()
    first = plan(rosdep, host.facts(), data)
    uploads = first.uploads()
    assert hashlib.sha256(uploads[ARCHIVE].encode("latin-1")).hexdigest()
    assert uploads["/etc/ros/rosdep/sources.list.d/20-default.list"].splitlines()[-1] == (
        f"yaml file://{rosdep_data.HOST_DIR}/sources/01-base.yaml")
    assert first.operation("follows the changed data").text() == [
        f"env ROSDISTRO_INDEX_URL=file://{rosdep_data.HOST_DIR}/rosdistro/index.yaml rosdep update"]
    host.apply(first)
    assert plan(rosdep, host.facts(), data).changing() == {}
