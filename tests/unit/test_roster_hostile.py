"""Roster values that must not get through (issue 18), table-driven through inventories/lab.py.

Each case writes a real roster (and the files it names), loads it exactly as
`pyinfra inventories/lab.py deploy.py` does, with every outgoing connection made to fail
the test, and asserts one line naming file:line, team, host and field, before any host
is contacted. The classes: text that means ASCII, controller paths outside their
purpose, YAML 1.1's implicit types, addresses no host or router can have, files that
are not regular files, names that do not exist (locales, time zones), and pyinfra's own
`--data` overrides.
"""

from __future__ import annotations

import json
import os
import runpy
import sys
import time
from pathlib import Path

import pytest

from roslab import settings
from roslab.roster import RosterError, load_roster

REPO = Path(__file__).resolve().parents[2]
LAB_INVENTORY = REPO / "inventories" / "lab.py"
KEY_LINE = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFlMtlfltx2Ordc++JZrFF/P0U8EAhdPijdaM3K81dM9 teacher"
PRIVATE_KEY = "-----BEGIN OPENSSH PRIVATE KEY-----\nstand-in\n-----END OPENSSH PRIVATE KEY-----\n"
WIFI_PASSWORD = "hunter2-PLANTED-password"

ROSTER = """\
classroom:
  ssh_user: ubuntu{classroom}
teams:
  team1:
    ros_domain_id: 11{team}
    hosts:
      team1-main:
        role: main{host}
"""
LINE = {"classroom": 3, "team": 6, "host": 9}
DOMAIN_LINE = 5  # a team's ros_domain_id replaces the template's own
WHERE = {"classroom": "", "team": "team 'team1', ", "host": "team 'team1', host 'team1-main', "}


@pytest.fixture
def classroom_dir(tmp_path, monkeypatch):
    """A roster's folder with the files rosters name: secrets, keys, a package, notes."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["pytest"])
    (tmp_path / "secrets.yaml").write_text(f"lab_wifi: {WIFI_PASSWORD}\n")
    (tmp_path / "secrets.yaml").chmod(0o600)
    (tmp_path / "notes.txt").write_text(f"the wifi password is {WIFI_PASSWORD}\n")
    (tmp_path / "teacher.pub").write_text(KEY_LINE + "\n")
    (tmp_path / "id_ed25519").write_text(PRIVATE_KEY)
    (tmp_path / "id_ed25519").chmod(0o600)
    (tmp_path / "nodes/pkg").mkdir(parents=True)
    (tmp_path / "nodes/pkg/package.xml").write_text("<package/>\n")
    (tmp_path / "empty").mkdir()
    (tmp_path / "ros2-apt-source.deb").write_bytes(b"!<arch>\n")
    (tmp_path / "20-default.list").write_text("yaml https://example.invalid/base.yaml\n")
    (tmp_path / "known_hosts").write_text(f"lab_wifi: {WIFI_PASSWORD}\n")  # named like one, it is not
    (tmp_path / "ok_known_hosts").write_text(f"# recorded\nteam1-main {KEY_LINE}\n")
    os.mkfifo(tmp_path / "fifo.pub")
    os.mkfifo(tmp_path / "fifo_known_hosts")
    os.mkfifo(tmp_path / "fifo_key")
    (tmp_path / "loop.pub").symlink_to(tmp_path / "loop2.pub")
    (tmp_path / "loop2.pub").symlink_to(tmp_path / "loop.pub")
    return tmp_path


def roster_text(level: str, key: str, value, raw: bool = False) -> str:
    indent = {"classroom": "  ", "team": "    ", "host": "        "}[level]
    shown = value if raw else json.dumps(value, ensure_ascii=False)
    if (level, key) == ("team", "ros_domain_id"):  # in place of the team's own, on the team's line
        return ROSTER.format(classroom="", team="", host="").replace(
            "    ros_domain_id: 11\n", f"    hosts_before: 0\n    ros_domain_id: {shown}\n").replace(
            "    hosts_before: 0\n", "")
    parts = {"classroom": "", "team": "", "host": ""}
    parts[level] = f"\n{indent}{key}: {shown}"
    return ROSTER.format(**parts)


def refused(directory: Path, text: str, monkeypatch, capsys, argv: list[str] | None = None) -> str:
    """Load `text` as the roster through inventories/lab.py; assert exit 2 quickly; the errors."""
    path = directory / "lab.yaml"
    if not path.is_fifo():
        path.write_text(text, encoding="utf-8")
    monkeypatch.setenv("ROSLAB_ROSTER", str(path))
    if argv is not None:
        monkeypatch.setattr(sys, "argv", ["pyinfra", "inventories/lab.py", "deploy.py", *argv])
    started = time.monotonic()
    with pytest.raises(SystemExit) as exited:
        runpy.run_path(str(LAB_INVENTORY))
    assert time.monotonic() - started < 5  # a guard: a FIFO, a device or a huge file never hangs the loader
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "no host was touched" in err
    assert "Traceback" not in err
    return err


def loads(directory: Path, text: str, monkeypatch):
    path = directory / "lab.yaml"
    path.write_text(text, encoding="utf-8")
    monkeypatch.setenv("ROSLAB_ROSTER", str(path))
    return runpy.run_path(str(LAB_INVENTORY))["_classroom"]


def level_of(key: str) -> str:
    levels = settings.SETTINGS[key].levels
    return "host" if "host" in levels else levels[-1]


def assert_refusal(err: str, level: str, key: str, *words: str) -> None:
    line = DOMAIN_LINE if (level, key) == ("team", "ros_domain_id") else LINE[level]
    prefix = f"lab.yaml:{line}: {WHERE[level]}field '{key}': "
    lines = [line for line in err.splitlines() if prefix in line]
    assert len(lines) == 1, err
    for word in words:
        assert word in lines[0], lines[0]
    assert WIFI_PASSWORD not in err


# --- text that means ASCII -----------------------------------------------------------------

DOTLESS_I, LONG_S, KELVIN = "\u0131", "\u017f", "\u212a"
ARABIC_ONE, FULLWIDTH_A, CYRILLIC_E = "\u0661", "\uff41", "\u0435"
NOT_ASCII = {
    "ssh_user": [f"ubuntu{LONG_S}", f"{KELVIN}ate"],
    "login_user": [f"student{DOTLESS_I}"],
    "apt_cache_host": [f"team1-ma{DOTLESS_I}n"],
    "address": [f"team1-ma{DOTLESS_I}n.local", f"10.0.0.{ARABIC_ONE}", f"{KELVIN}.example"],
    "locale": [f"en_US.UTF-{ARABIC_ONE}", f"de_DE{LONG_S}.UTF-8"],
    "timezone": [f"Europe/Berl{DOTLESS_I}n", f"Etc/GMT+{ARABIC_ONE}"],
    "network_interface": [f"eth{ARABIC_ONE}", f"wlan{FULLWIDTH_A}"],
    "network_address": [f"10.0.0.{ARABIC_ONE}/24"],
    "network_gateway": [f"10.0.0.{ARABIC_ONE}"],
    "ros_apt_source_version": [f"1.2.{ARABIC_ONE}"],
    "ros_static_peers": [[f"team1-ma{DOTLESS_I}n"]],
    "ros_extra_packages": [[f"ros-{{distro}}-turtle{LONG_S}im"]],
    "rosdep_package": [f"python3-rosdep{DOTLESS_I}"],
    "workspace_dir": [f"~/w{LONG_S}"],
    "workspace_colcon_args": [[f"--executor{KELVIN}"]],
    "nodes_launch_main": [f"roslab_bringup ma{DOTLESS_I}n.launch.py"],
    "nodes_verify_topic": [f"/chatter{KELVIN}"],
    "rosdistro_index_url": [f"https://exampl{CYRILLIC_E}.com/index.yaml"],
    "ros_apt_mirror_url": [f"http://m{DOTLESS_I}rror/ros2"],
    "wifi_password_secret": [f"lab_wif{DOTLESS_I}"],
    "ros_apt_source_sha256": [{"noble": "0" * 63 + ARABIC_ONE}],
}


@pytest.mark.parametrize("key, value", [(k, v) for k, values in NOT_ASCII.items() for v in values],
                         ids=lambda item: item if isinstance(item, str) and item in settings.SETTINGS else None)
def test_text_that_means_ascii_refuses_lookalikes(key, value, classroom_dir, monkeypatch, capsys, no_connections):
    level = level_of(key)
    err = refused(classroom_dir, roster_text(level, key, value), monkeypatch, capsys)
    assert_refusal(err, level, key)
    assert no_connections == []


@pytest.mark.parametrize("name", [f"team1-ma{DOTLESS_I}n", f"team1-{LONG_S}", f"team1-{KELVIN}",
                                  f"team{ARABIC_ONE}-main", f"te{FULLWIDTH_A}m1"])
def test_a_host_name_with_a_lookalike_letter_is_refused(name, classroom_dir, monkeypatch, capsys, no_connections):
    text = ROSTER.format(classroom="", team="", host="").replace("team1-main:", f'"{name}":')
    err = refused(classroom_dir, text, monkeypatch, capsys)
    assert f"lab.yaml:7: team 'team1', host '{name}': " in err
    assert "not an ASCII character" in err


@pytest.mark.parametrize("name", [f"team{DOTLESS_I}", f"{KELVIN}lass", f"team{ARABIC_ONE}"])
def test_a_team_name_with_a_lookalike_letter_is_refused(name, classroom_dir, monkeypatch, capsys):
    text = ROSTER.format(classroom="", team="", host="").replace("  team1:", f'  "{name}":')
    err = refused(classroom_dir, text, monkeypatch, capsys)
    assert f"lab.yaml:4: team '{name}': a team name starts with a letter" in err


def test_every_regex_that_reads_roster_values_means_ascii():
    """No module that checks roster values compiles a pattern that matches non-ASCII text by accident."""
    import ast

    offenders = []
    modules = [REPO / "roslab/formats.py", REPO / "roslab/network/settings.py", REPO / "roslab/network/apply.py",
               *(REPO / "roslab/roster").glob("*.py"), *(REPO / "roslab/seed").glob("*.py")]
    for path in modules:
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and isinstance(node.func.value, ast.Name) and node.func.value.id == "re"
                    and node.func.attr in ("compile", "fullmatch", "match", "search")):
                continue
            source = ast.unparse(node)
            flags = " ".join(ast.unparse(arg) for arg in [*node.args[1:], *(k.value for k in node.keywords)])
            pattern_text = ast.unparse(node.args[0]) if node.args else ""
            if "IGNORECASE" in flags and "ASCII" not in flags:
                offenders.append(f"{path.name}: {source}")
            if any(cls in pattern_text for cls in ("\\\\d", "\\\\w", "\\\\s", "\\\\b")) and "ASCII" not in flags:
                offenders.append(f"{path.name}: {source}")
    assert offenders == []


def test_roslab_seed_reports_a_lookalike_host_name_without_a_traceback(classroom_dir, capsys, no_connections):
    from roslab.cli.main import main

    path = classroom_dir / "lab.yaml"
    path.write_text(ROSTER.format(classroom="", team="", host="").replace("team1-main:", f"team1-ma{DOTLESS_I}n:"),
                    encoding="utf-8")
    assert main(["seed", str(path), "--out", str(classroom_dir / "seeds")]) == 1
    err = capsys.readouterr().err
    assert "not an ASCII character" in err and "Traceback" not in err
    assert not (classroom_dir / "seeds").exists()


# --- controller paths: each has a purpose and a place ------------------------------------------

BAD_PATHS = {
    "ssh_known_hosts_file": [("secrets.yaml", "name must end in known_hosts"),
                             ("notes.txt", "name must end in known_hosts"),
                             ("lab.yaml", "name must end in known_hosts"),
                             ("known_hosts", "line 1 is not a host key line"),
                             ("fifo_known_hosts", "FIFO"),
                             ("/etc/passwd", "name must end in known_hosts")],
    "workspace_nodes_dir": [("/", "name the folder"), ("~", "name the folder"),
                            (".", "holds the roster's folder"), ("..", "holds the roster's folder"),
                            ("empty", "holds no ROS package")],
    "ros_apt_source_url": [("file:///etc/passwd", ".deb"),
                           ("file:///var/cache/apt/archives/x.deb", "outside the roster's folder"),
                           ("file://{dir}/../x.deb", "without '..'"),
                           ("file://elsewhere/{dir}/ros2-apt-source.deb", "on this machine only")],
    "rosdep_sources_list_url": [("file:///etc/shadow", ".list"),
                                ("file:///etc/apt/sources.list", "outside the roster's folder"),
                                ("file://{dir}/.roslab-state/x.list", "outside the roster's folder")],
    "secrets_file": [("/etc/roslab-secrets.yaml", "outside the roster's folder"),
                     ("../secrets.yaml", "outside the roster's folder"),
                     ("lab.yaml", "the roster itself"),
                     (".roslab-state/secrets.yaml", "outside the roster's folder"),
                     ("notes.txt", "is not a .yaml file")],
    "ssh_key": [("notes.txt", "not an SSH private key"), ("fifo_key", "FIFO"), ("nodes", "a directory"),
                ("/dev/zero", "character device")],
    "ros_apt_mirror_key_file": [("notes.txt", "not an OpenPGP public key"), ("/dev/zero", "character device")],
    "teacher_ssh_keys": [(["secrets.yaml"], "nor a readable .pub file"), (["/etc/passwd"], ".pub file"),
                         (["fifo.pub"], "FIFO"), (["loop.pub"], "symlink loop")],
    "rosdep_cache_dir": [("/", "not a folder of its own"), ("/etc/roslab", "not a folder of its own"),
                         ("~", "not a folder of its own"), ("~/.ssh/roslab", "not a cache"),
                         (".roslab-state/cache", "not a cache")],
    "ros_apt_source_cache_dir": [("/usr/lib/roslab", "not a folder of its own")],
}


@pytest.mark.parametrize("key, value, words",
                         [(key, value, words) for key, cases in BAD_PATHS.items() for value, words in cases],
                         ids=lambda item: item if isinstance(item, str) and item in settings.SETTINGS else None)
def test_a_controller_path_outside_its_purpose_is_refused(key, value, words, classroom_dir, monkeypatch,
                                                          capsys, no_connections):
    if isinstance(value, str):
        value = value.replace("{dir}", str(classroom_dir))
    level = level_of(key)
    err = refused(classroom_dir, roster_text(level, key, value), monkeypatch, capsys)
    assert_refusal(err, level, key, words)
    assert no_connections == []


def test_controller_paths_in_their_place_are_taken(classroom_dir, monkeypatch, no_connections):
    text = ROSTER.format(classroom=(
        "\n  ssh_known_hosts_file: ok_known_hosts"
        "\n  ssh_key: id_ed25519"
        "\n  teacher_ssh_keys: [teacher.pub]"
        "\n  workspace_nodes_dir: nodes"
        f"\n  ros_apt_source_url: file://{classroom_dir}/ros2-apt-source.deb"
        f"\n  rosdep_sources_list_url: file://{classroom_dir}/20-default.list"
        "\n  rosdep_cache_dir: ~/.cache/roslab/rosdep-test"
        "\n  ros_apt_source_cache_dir: cache/ros-apt-source"), team="", host="")
    host = loads(classroom_dir, text, monkeypatch).hosts[0]
    assert host.data["ssh_known_hosts_file"] == str(classroom_dir / "ok_known_hosts")
    assert host.data["workspace_nodes_dir"] == str(classroom_dir / "nodes")
    assert host.data["teacher_ssh_keys"] == [KEY_LINE]
    assert no_connections == []


def test_a_known_hosts_file_of_dev_null_is_taken(classroom_dir, monkeypatch):
    text = roster_text("classroom", "ssh_known_hosts_file", "/dev/null") \
        .replace("ssh_user: ubuntu", 'ssh_user: ubuntu\n  ssh_strict_host_key_checking: "no"')
    assert loads(classroom_dir, text, monkeypatch).hosts[0].data["ssh_known_hosts_file"] == "/dev/null"


# --- YAML 1.1's implicit types ---------------------------------------------------------------

YAML_VALUES = [
    ("team", "ros_domain_id", "011", "octal number 9: write 11"),
    ("team", "ros_domain_id", "08", "write 8"),
    ("team", "ros_domain_id", "0x1A", "base 16"),
    ("team", "ros_domain_id", "1_0", "write 10"),
    ("team", "ros_domain_id", "1:30", "base-60 number 90"),
    ("host", "ssh_port", "0o22", "base 8"),
    ("host", "ssh_port", "02222", "write 2222"),
    ("classroom", "network_prefix", "024", "write 24"),
    ("host", "wifi_ssid", "on", 'quote it, "on"'),
    ("host", "wifi_ssid", "Off", 'quote it, "Off"'),
    ("classroom", "name", "yes", 'quote it, "yes"'),
    ("host", "network_ipv6", "off", 'quote it, "off"'),
    ("classroom", "apt_extra_suites", "[updates, on]", "holds 'on'"),
    ("classroom", "ros_static_peers", "[10.0.0.1, 010]", "holds '010'"),
    ("classroom", "apt_cache_upstream_ports", "[80, 08080]", "write 8080"),
]


@pytest.mark.parametrize("level, key, raw, words", YAML_VALUES, ids=lambda item: str(item))
def test_a_value_yaml_reads_two_ways_is_refused_with_what_to_write(level, key, raw, words, classroom_dir,
                                                                   monkeypatch, capsys, no_connections):
    err = refused(classroom_dir, roster_text(level, key, raw, raw=True), monkeypatch, capsys)
    assert_refusal(err, level, key, words)
    assert "remove the quotes" not in err


@pytest.mark.parametrize("raw", ["0x", "0o9", "0b2", "0xg1", "0b1a", "0o7z"])
def test_text_that_only_starts_like_a_number_in_another_base_is_plain_text(raw):
    """0b wants binary digits, 0o octal and 0x hex ones: anything else is text to every YAML reader."""
    import yaml

    from roslab.checked.loading import Ambiguous, StrictLoader

    value = yaml.load(f"v: {raw}\n", Loader=StrictLoader)["v"]
    assert value == raw and not isinstance(value, Ambiguous)
    for number in ("0x1A", "0b101", "0o17"):
        assert isinstance(yaml.load(f"v: {number}\n", Loader=StrictLoader)["v"], Ambiguous)


def test_a_sha256_that_begins_with_0b_is_taken_as_written(classroom_dir, monkeypatch):
    """The apt source's sha256 (64 hex digits) may begin 0b... or 0e...: text, as written."""
    digest = "0ba59f19e2f4a5031f4125a4f2b0c2e866b86bd75c48ec1047b55e0f0d163eb1"
    text = roster_text("classroom", "ros_apt_source_sha256", f"{{noble: {digest}}}", raw=True)
    assert loads(classroom_dir, text, monkeypatch).hosts[0].data["ros_apt_source_sha256"]["noble"] == digest


@pytest.mark.parametrize("where, name", [("team", "yes"), ("team", "null"), ("team", "on"), ("team", "~"),
                                         ("team", "true"), ("host", "yes"), ("host", "no"), ("host", "null"),
                                         ("host", "Off")])
def test_a_team_or_host_named_like_a_yaml_value_must_be_quoted(where, name, classroom_dir, monkeypatch, capsys):
    text = ROSTER.format(classroom="", team="", host="")
    text = text.replace("  team1:", f"  {name}:") if where == "team" else text.replace("team1-main:", f"{name}:")
    err = refused(classroom_dir, text, monkeypatch, capsys)
    line = 4 if where == "team" else 7
    assert f"lab.yaml:{line}: team " in err
    assert "quote it" in err


def test_a_setting_key_yaml_reads_as_a_value_is_refused(classroom_dir, monkeypatch, capsys):
    err = refused(classroom_dir, roster_text("classroom", "on", "x"), monkeypatch, capsys)
    assert "lab.yaml:3: the key 'on' is ambiguous" in err and 'quote it, "on"' in err


@pytest.mark.parametrize("level, key, raw, meant", [
    ("classroom", "offline", "yes", True),
    ("classroom", "locale_enabled", "off", False),
    ("classroom", "ssh_strict_host_key_checking", "no", "no"),
    ("classroom", "ssh_strict_host_key_checking", "off", "off"),
    ("team", "ros_domain_id", "0", 0),
    ("host", "ssh_port", "2222", 2222),
    ("classroom", "name", "2024-09-01", "2024-09-01"),
])
def test_what_the_teacher_wrote_is_what_the_hosts_get(level, key, raw, meant, classroom_dir, monkeypatch):
    host = loads(classroom_dir, roster_text(level, key, raw, raw=True), monkeypatch).hosts[0]
    if key == "name":
        return  # the classroom's name is not host data; loading is the point
    assert host.data[key] == meant and type(host.data[key]) is type(meant)


def test_a_quoted_number_with_a_leading_zero_says_what_to_write(classroom_dir, monkeypatch, capsys):
    err = refused(classroom_dir, roster_text("team", "ros_domain_id", '"08"', raw=True), monkeypatch, capsys)
    assert_refusal(err, "team", "ros_domain_id", "write 8, without quotes")


# --- addresses no host or router can have ------------------------------------------------------

ADDRESS_CASES = [
    ("network_gateway", "10.0.0.0", "network address of 10.0.0.0/24"),
    ("network_gateway", "10.0.0.255", "broadcast address of 10.0.0.0/24"),
    ("network_gateway", "127.0.0.1", "loopback"),
    ("network_gateway", "224.0.0.1", "multicast"),
    ("network_gateway", "0.0.0.0", "unspecified"),
    ("network_gateway", "255.255.255.255", "not a router's address"),
    ("network_address", "127.0.0.5/8", "loopback"),
    ("network_address", "224.0.0.5/24", "multicast"),
    ("network_address", "240.0.0.5/24", "reserved"),
    ("network_address", "169.254.0.5/16", "link-local"),
    ("network_address", "10.0.0.0/24", "network address"),
    ("network_address", "10.0.0.255/24", "broadcast address"),
    ("network_nameservers", ["0.0.0.0"], "not an IP address"),
    ("network_nameservers", ["224.0.0.251"], "not an IP address"),
    ("address", "0.0.0.0", "not an address a host can have"),
    ("address", "255.255.255.255", "not an address a host can have"),
    ("address", "ff02::1", "not an address a host can have"),
    ("ros_static_peers", ["224.0.0.1"], "not an address a host can have"),
]


@pytest.mark.parametrize("key, value, words", ADDRESS_CASES, ids=lambda item: str(item))
def test_an_address_no_host_or_router_can_have_is_refused(key, value, words, classroom_dir, monkeypatch, capsys,
                                                          no_connections):
    extra = {"network_address": "10.0.0.5/24", key: value}
    host = "".join(f"\n        {k}: {json.dumps(v)}" for k, v in extra.items())
    err = refused(classroom_dir, ROSTER.format(classroom="", team="", host=host), monkeypatch, capsys)
    line = [line for line in err.splitlines() if f"field '{key}'" in line]
    assert len(line) == 1 and words in line[0], err
    assert "team 'team1', host 'team1-main'" in line[0]


# --- files that are not regular files, and sizes ---------------------------------------------------

@pytest.mark.parametrize("kind, words", [("fifo", "is a FIFO"), ("device", "is a character device"),
                                         ("directory", "is a directory"), ("loop", "symlink loop"),
                                         ("huge", "larger than 1 MiB")])
def test_a_roster_that_is_not_a_regular_file_is_one_line_at_once(kind, words, classroom_dir, monkeypatch, capsys):
    path = classroom_dir / "lab.yaml"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        path.symlink_to("/dev/zero")
    elif kind == "directory":
        path.mkdir()
    elif kind == "loop":
        path.symlink_to(classroom_dir / "other.yaml")
        (classroom_dir / "other.yaml").symlink_to(path)
    else:
        with path.open("w") as out:
            out.write(("# a comment line of a file far bigger than any roster\n" * 50_000))
    err = refused(classroom_dir, "", monkeypatch, capsys) if kind == "fifo" else None
    if err is None:
        monkeypatch.setenv("ROSLAB_ROSTER", str(path))
        started = time.monotonic()
        with pytest.raises(SystemExit):
            runpy.run_path(str(LAB_INVENTORY))
        assert time.monotonic() - started < 5  # a guard against a hang, not a benchmark
        err = capsys.readouterr().err
    problems = [line for line in err.splitlines() if "lab.yaml" in line]
    assert len(problems) == 1 and words in problems[0], err


@pytest.mark.parametrize("kind", ["fifo", "device", "directory", "huge"])
def test_a_secrets_file_that_is_not_a_regular_file_is_one_line_at_once(kind, classroom_dir, monkeypatch, capsys):
    secrets = classroom_dir / "secrets.yaml"
    secrets.unlink()
    if kind == "fifo":
        os.mkfifo(secrets, 0o600)
    elif kind == "device":
        secrets.symlink_to("/dev/zero")
    elif kind == "directory":
        secrets.mkdir(mode=0o700)
    else:
        secrets.write_text("# padding\n" * 20_000)
        secrets.chmod(0o600)
    text = roster_text("host", "wifi_password_secret", "lab_wifi")
    err = refused(classroom_dir, text, monkeypatch, capsys)
    assert "secrets" in err and "Traceback" not in err


def test_a_list_longer_than_any_classroom_needs_is_refused(classroom_dir, monkeypatch, capsys):
    packages = [f"ros-jazzy-p{index}" for index in range(settings.MAX_ITEMS + 1)]
    err = refused(classroom_dir, roster_text("classroom", "ros_extra_packages", packages), monkeypatch, capsys)
    assert_refusal(err, "classroom", "ros_extra_packages", f"at most {settings.MAX_ITEMS}")


# --- names that must exist ------------------------------------------------------------------------

@pytest.mark.parametrize("key, value, words", [
    ("locale", "xx_YY.UTF-8", "not a UTF-8 locale glibc supports"),
    ("locale", "en_DE.UTF-8", "not a UTF-8 locale glibc supports"),
    ("locale", "ca_ES.UTF-8@bogus", "did you mean 'ca_ES.UTF-8'"),
    ("locale", "de_DE.ISO-8859-1", "a UTF-8 locale name"),
    ("timezone", "Mars/Olympus_Mons", "not a time zone in the tz database"),
    ("timezone", "Europe/Berlim", "did you mean 'Europe/Berlin'"),
    ("timezone", "Europe/Atlantis", "not a time zone"),
    ("timezone", "localtime", "not a time zone"),
    ("timezone", "Etc/GMT+14", "not a time zone"),
])
def test_a_locale_or_time_zone_that_does_not_exist_is_refused(key, value, words, classroom_dir, monkeypatch,
                                                              capsys, no_connections):
    level = level_of(key)
    err = refused(classroom_dir, roster_text(level, key, value), monkeypatch, capsys)
    assert_refusal(err, level, key, words)


@pytest.mark.parametrize("key, value", [("locale", "ca_ES.UTF-8@valencia"), ("locale", "C.UTF-8"),
                                        ("locale", "de_CH.UTF-8"), ("timezone", "America/Argentina/Buenos_Aires"),
                                        ("timezone", "Etc/GMT+5"), ("timezone", "UTC")])
def test_real_locales_and_time_zones_are_taken(key, value, classroom_dir, monkeypatch):
    assert loads(classroom_dir, roster_text(level_of(key), key, value), monkeypatch).hosts[0].data[key] == value


# --- pyinfra's --data (and --user, --port, --key) --------------------------------------------------

@pytest.mark.parametrize("argv, key, words", [
    (["--data", "ros_domain_id=999"], "ros_domain_id", "outside 0 to 101"),
    (["--data=ros_domain_id=011"], "ros_domain_id", "write 11"),
    (["--data", f"ros_domain_id=1{ARABIC_ONE}"], "ros_domain_id", "not ASCII"),
    (["--data", "locale=xx_YY.UTF-8"], "locale", "not a UTF-8 locale"),
    (["--data", "workspace_nodes_dir=/"], "workspace_nodes_dir", "name the folder"),
    (["--data", "ssh_known_hosts_file=secrets.yaml"], "ssh_known_hosts_file", "known_hosts"),
    (["--data", "workspace_nodes_dir=nodes"], "workspace_nodes_dir", "give an absolute path"),
    (["--data", "ros_domian_id=5"], "ros_domian_id", "did you mean 'ros_domain_id'"),
    (["--data", "role=robot"], "role", "per host in the roster"),
    (["--data", "wifi_password_secret=lab_wifi"], "wifi_password_secret", "set in the roster"),
    (["--data", "ssh_hostname=10.1.2.3"], "ssh_hostname", "roslab decides where each host is"),
    (["--data", "_sudo_password=x"], "_sudo_password", "sudo_password_secret"),
    (["--data", "roslab_team=team9"], "roslab_team", "derives it"),
    (["--port", "0"], "ssh_port", "outside 1 to 65535"),
    (["--user", "-oProxyCommand=x"], "ssh_user", "Linux user name"),
    (["--key", "notes.txt"], "ssh_key", "not an SSH private key"),
    (["--password", "x"], "ssh_password", "--ssh-password-prompt"),
])
def test_a_pyinfra_data_override_is_checked_like_the_roster(argv, key, words, classroom_dir, monkeypatch, capsys,
                                                            no_connections):
    err = refused(classroom_dir, ROSTER.format(classroom="", team="", host=""), monkeypatch, capsys, argv=argv)
    lines = [line for line in err.splitlines() if line.startswith(f"pyinfra's command line: field '{key}': ")]
    assert len(lines) == 1 and words in lines[0], err
    assert no_connections == []


def test_pyinfra_data_overrides_that_pass_reach_every_host(classroom_dir, monkeypatch, no_connections):
    monkeypatch.setattr(sys, "argv", ["pyinfra", "inventories/lab.py", "deploy.py", "--data", "ros_domain_id=12",
                                      "--data", "_sudo_user=nobody", "--data",
                                      f"workspace_nodes_dir={classroom_dir / 'nodes'}"])
    host = loads(classroom_dir, ROSTER.format(classroom="", team="", host=""), monkeypatch).hosts[0]
    assert host.data["ros_domain_id"] == 12 and host.ros_domain_id == 12
    assert host.data["workspace_nodes_dir"] == str(classroom_dir / "nodes")


def test_one_domain_for_two_teams_from_the_command_line_is_refused(classroom_dir, monkeypatch, capsys):
    text = ROSTER.format(classroom="", team="", host="") + (
        "  team2:\n    ros_domain_id: 12\n    hosts:\n      team2-main:\n        role: main\n")
    err = refused(classroom_dir, text, monkeypatch, capsys, argv=["--data", "ros_domain_id=5"])
    assert "ROS_DOMAIN_ID 5 is already team 'team1'" in err


def test_the_roster_loader_never_raises_on_a_hostile_file(classroom_dir):
    """Direct load_roster calls (roslab check, seed, status) get the same one-line problems."""
    path = classroom_dir / "lab.yaml"
    os.mkfifo(path)
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert len(raised.value.problems) == 1 and "FIFO" in str(raised.value)


CLI_TEXTS = ["true", "False", "12", "011", "-3", "[1, 2]", '{"a": 1}', "x=y", "1.5", "", "\u0661"]


def test_command_line_values_are_read_as_pyinfra_reads_them():
    """roslab mirrors pyinfra's parse_cli_arg (pyinfra_cli is not imported in-process): same values."""
    import subprocess

    from roslab.roster import overrides

    theirs = subprocess.run(
        [sys.executable, "-c", "import json, sys; from pyinfra_cli.util import parse_cli_arg; "
                               "print(json.dumps([parse_cli_arg(text) for text in sys.argv[1:]]))", *CLI_TEXTS],
        capture_output=True, text=True, check=True).stdout
    ours = [overrides.command_line_data(["pyinfra", "--data", f"k={text}"])[0][3] for text in CLI_TEXTS]
    assert json.loads(theirs) == ours


# --- roslab seed: any value the roster takes makes a seed, any other is one line ------------------

@pytest.mark.parametrize("key, raw", [
    ("name", '"\\ud800"'), ("wifi_ssid", '"lab\\udfff"'), ("teacher_ssh_keys", f'["{KEY_LINE} \\ud800"]'),
    ("timezone", '"Europe/Berlin\\ud800"'),
])
def test_a_lone_surrogate_is_refused_as_not_text(key, raw, classroom_dir, monkeypatch, capsys):
    level = level_of(key)
    err = refused(classroom_dir, roster_text(level, key, raw, raw=True), monkeypatch, capsys)
    assert_refusal(err, level, key)


def test_roslab_seed_writes_unicode_where_the_roster_allows_it(classroom_dir, monkeypatch, capsys, no_connections):
    """Text that may hold any letter (a classroom's name, an SSID, a key's comment) makes a valid
    seed: the documents are built, encoded and dumped without a traceback."""
    import yaml

    from roslab.seed.documents import host_seed

    (classroom_dir / "secrets.yaml").write_text("lab_wifi: 'pässwörd-ok'\n".replace("ä", "a").replace("ö", "o"))
    text = ROSTER.format(
        classroom=f'\n  name: "Klasse {DOTLESS_I} {KELVIN} ✓"\n  teacher_ssh_keys: ["{KEY_LINE} {LONG_S}✓"]'
                  '\n  timezone: Europe/Istanbul\n  locale: tr_TR.UTF-8',
        team="", host='\n        network_kind: wifi\n        wifi_ssid: "Café ıſ ✓"\n'
                      '        wifi_password_secret: lab_wifi\n        network_address: 10.0.0.5/24')
    classroom = loads(classroom_dir, text, monkeypatch)
    files = host_seed(classroom.hosts[0], classroom_dir / "lab.yaml")
    user = yaml.safe_load(files["user-data"].content.decode("utf-8"))
    assert user["hostname"] == "team1-main" and user["timezone"] == "Europe/Istanbul"
    assert f"{KEY_LINE} {LONG_S}✓" in str(user)
    assert "Café ıſ ✓" in files["network-config"].content.decode("utf-8")


@pytest.mark.parametrize("listed", ["file:///etc/passwd", "../outside.yaml", "file://{root}/../outside.yaml",
                                    "ftp://mirror/base.yaml"])
def test_rosdep_data_never_fetches_a_controller_file_outside_the_given_folder(listed, tmp_path, no_connections):
    """A sources list may list files too: what it lists is copied to every Pi, so a file:// URL
    stays inside the folder of the file:// URL the roster gave."""
    from roslab import downloads
    from roslab.ros import rosdep_data

    root = tmp_path / "offline"
    root.mkdir()
    (tmp_path / "outside.yaml").write_text(f"secret: {WIFI_PASSWORD}\n")
    (root / "20-default.list").write_text(f"yaml {listed.replace('{root}', str(root))}\n")
    (root / "index.yaml").write_text("type: index\nversion: 4\ndistributions: {jazzy: {distribution: []}}\n")
    downloads._fetched.clear()
    rosdep_data._built.clear()
    try:
        with pytest.raises(rosdep_data.RosdepDataError) as raised:
            rosdep_data.for_distro(f"file://{root}/20-default.list", f"file://{root}/index.yaml", "jazzy",
                                   tmp_path / "cache")
    finally:
        downloads._fetched.clear()
        rosdep_data._built.clear()
    assert "rosdep's data lists" in str(raised.value) and WIFI_PASSWORD not in str(raised.value)


HOSTILE_TEXT = [f"team1-ma{DOTLESS_I}n", f"x{KELVIN}", "\ud800", "a\u2028b", "\u202eevil", "caf\u00e9 \u2713",
                "\ufeffBOM", "x" * 300]


@pytest.mark.parametrize("setting", [s for s in settings.SCHEMA if s.kind is str or s.item is str],
                         ids=lambda s: s.key)
def test_roslab_seed_never_raises_on_any_text_value(setting, classroom_dir, capsys, no_connections):
    """Every text setting, with look-alikes, a surrogate, a line separator, bidi controls:
    either the roster refuses it in one line, or the seed's documents are built and dumped."""
    from roslab.seed.documents import SeedError, authorized_keys, host_seed, network_config

    level = level_of(setting.key)
    for value in HOSTILE_TEXT:
        path = classroom_dir / "lab.yaml"
        written = [value] if setting.item is str else value
        # JSON's \\u escapes are YAML's too: a surrogate reaches the loader as the escape a file can hold.
        text = roster_text(level, setting.key, json.dumps(written), raw=True) if setting.key != "role" else \
            ROSTER.format(classroom="", team="", host="").replace("role: main", f"role: {json.dumps(value)}")
        text = text.replace("ssh_user: ubuntu", f"ssh_user: ubuntu\n  teacher_ssh_keys: [{json.dumps(KEY_LINE)}]", 1) \
            if setting.key != "teacher_ssh_keys" else text
        path.write_text(text, encoding="utf-8")
        try:
            classroom = load_roster(path)
        except RosterError as error:
            assert all(str(problem).startswith("lab.yaml") for problem in error.problems)
            continue
        for host in classroom.hosts:
            try:
                authorized_keys(host)
                network_config(host)
            except SeedError:
                continue
            files = host_seed(host, path)
            assert files["user-data"].content.decode("utf-8").startswith("#cloud-config")


@pytest.mark.parametrize("raw", ["!!int 011", "!!float 1", "!!bool yes", "!!binary aGk=", "!!timestamp 2024-01-01",
                                 "!!set {a, b}", "!custom x", "!!python/name:os.system"])
def test_an_explicit_yaml_tag_is_refused(raw, classroom_dir, monkeypatch, capsys):
    err = refused(classroom_dir, roster_text("team", "ros_domain_id", raw, raw=True), monkeypatch, capsys)
    assert f"lab.yaml:{DOMAIN_LINE}: not valid YAML: the tag " in err and "has no place in a roster" in err


def test_a_str_tag_is_another_way_to_quote(classroom_dir, monkeypatch):
    host = loads(classroom_dir, roster_text("host", "wifi_ssid", "!!str yes", raw=True), monkeypatch).hosts[0]
    assert host.data["wifi_ssid"] == "yes"


def test_the_default_secrets_file_keeps_to_the_rosters_folder_too(classroom_dir, monkeypatch, capsys, tmp_path_factory):
    elsewhere = tmp_path_factory.mktemp("elsewhere") / "secrets.yaml"
    elsewhere.write_text(f"lab_wifi: {WIFI_PASSWORD}\n")
    elsewhere.chmod(0o600)
    (classroom_dir / "secrets.yaml").unlink()
    (classroom_dir / "secrets.yaml").symlink_to(elsewhere)
    err = refused(classroom_dir, roster_text("host", "wifi_password_secret", "lab_wifi"), monkeypatch, capsys)
    assert "field 'secrets_file': the default secrets file: 'secrets.yaml' leads outside the roster's folder" in err
    assert WIFI_PASSWORD not in err


def test_pyinfras_own_command_line_is_checked_before_it_connects(tmp_path):
    """The real pyinfra CLI (a child process: importing pyinfra_cli patches this one with gevent):
    `--data ros_domain_id=999` stops at the inventory with exit 2, naming the option; the host
    (loopback, a port nothing listens on) is never reached."""
    import subprocess

    roster = tmp_path / "lab.yaml"
    roster.write_text(ROSTER.format(classroom="", team="", host="\n        address: 127.0.0.1\n        ssh_port: 9"))
    run = subprocess.run([str(Path(sys.executable).parent / "pyinfra"), "inventories/lab.py", "deploy.py", "--dry",
                          "--data", "ros_domain_id=999"], cwd=REPO, env={**os.environ, "ROSLAB_ROSTER": str(roster)},
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stdout + run.stderr
    assert ("pyinfra's command line: field 'ros_domain_id': --data ros_domain_id=999: "
            "ROS_DOMAIN_ID 999 is outside") in run.stderr
    assert "Connecting" not in run.stdout + run.stderr and "--> Preparing" not in run.stdout + run.stderr
