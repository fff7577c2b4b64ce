"""`roslab check`: what a teacher sees, and the exit status scripts rely on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from roslab.cli.main import TABLE_COLUMNS, main

REPO = Path(__file__).resolve().parents[2]
FIXTURE = Path(__file__).parent / "rosters" / "two_teams.yaml"
SECRET_VALUE = "correct-horse-battery"


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch):
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)


def test_check_prints_the_classroom_as_aligned_columns(capsys):
    assert main(["check", str(FIXTURE)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("Classroom 'fixture-lab'") and "2 teams, 3 hosts" in out[0]
    header, *rows = out[1:]
    assert header.split() == list(TABLE_COLUMNS)
    assert [row.split() for row in rows] == [
        ["team1", "team1-main", "main", "127.0.0.11", "24.04", "jazzy", "desktop", "11", "multicast", "demo"],
        ["team1", "team1-robot", "robot", "127.0.0.12", "24.04", "jazzy", "ros-base", "11", "multicast", "demo"],
        ["team-2", "team2-main", "main", "127.0.0.21", "22.04", "humble", "desktop", "12", "multicast", "demo"],
    ]
    assert out[0].endswith(", middleware rmw_fastrtps_cpp")
    # Every column starts at the same offset on every line.
    for column in TABLE_COLUMNS[1:]:
        offset = header.index(column)
        assert all(row[offset - 2:offset] == "  " and row[offset] != " " for row in rows)


def test_check_with_errors_exits_1_and_lists_them_on_stderr(tmp_path, capsys):
    roster = tmp_path / "bad.yaml"
    roster.write_text(textwrap.dedent("""\
        teams:
          t:
            hosts:
              t-main: {role: main, ros_distr: jazzy}
              t-robot: {role: robot, address: 10.0.0.300}
    """))
    assert main(["check", str(roster)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    errors = captured.err.splitlines()
    assert "host 't-main', field 'ros_distr': unknown key" in errors[0]
    assert "host 't-robot', field 'address':" in errors[1]
    assert errors[-1] == "roslab check: 2 errors in the roster; no host was touched, nothing was written"


def test_check_never_prints_a_secret(tmp_path, capsys):
    secrets_file = tmp_path / "secrets.yaml"
    secrets_file.write_text(f"wifi: {SECRET_VALUE}\n")
    secrets_file.chmod(0o600)
    roster = tmp_path / "lab.yaml"
    roster.write_text("classroom: {wifi_password_secret: wifi}\n"
                      "teams: {t: {hosts: {t-main: {role: main}}}}\n")
    assert main(["check", str(roster)]) == 0
    secrets_file.chmod(0o644)
    assert main(["check", str(roster)]) == 1
    captured = capsys.readouterr()
    assert "chmod 600" in captured.err
    assert SECRET_VALUE not in captured.out + captured.err


def test_check_uses_roslab_roster_from_the_environment(monkeypatch, capsys):
    monkeypatch.setenv("ROSLAB_ROSTER", str(FIXTURE))
    assert main(["check"]) == 0
    assert "fixture-lab" in capsys.readouterr().out


def test_usage_error_exits_2(capsys):
    with pytest.raises(SystemExit) as raised:
        main(["chekc"])
    assert raised.value.code == 2
    assert "invalid choice: 'chekc'" in capsys.readouterr().err


def test_python_dash_m_roslab_checks_the_example_roster():
    env = {key: value for key, value in os.environ.items() if key != "ROSLAB_ROSTER"}
    result = subprocess.run([sys.executable, "-m", "roslab", "check"], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "Classroom 'robotics-lab' (inventories/" in result.stdout
    assert "team2-robot2" in result.stdout


def _pyinfra_debug_inventory(roster: Path, *extra: str) -> subprocess.CompletedProcess:
    # debug-inventory prints the inventory and connects to nothing.
    pyinfra = Path(sys.executable).with_name("pyinfra")
    env = {**os.environ, "ROSLAB_ROSTER": str(roster)}
    return subprocess.run([str(pyinfra), "inventories/lab.py", *extra, "debug-inventory"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=60)


def test_pyinfra_inventory_has_the_roster_groups():
    result = _pyinfra_debug_inventory(FIXTURE)
    assert result.returncode == 0, result.stderr
    assert "[team2-main]" in result.stderr
    assert "--> Groups: main, team_2, humble" in result.stderr


def test_pyinfra_stops_on_a_bad_roster_before_connecting(tmp_path):
    roster = tmp_path / "bad.yaml"
    roster.write_text("teams: {t: {hosts: {t-main: {role: main, ros_domain_id: 999}}}}\n")
    result = _pyinfra_debug_inventory(roster)
    assert result.returncode == 2
    assert "the roster has errors, no host was touched" in result.stderr
    assert "field 'ros_domain_id'" in result.stderr
    assert "[t-main]" not in result.stderr


# Run in a child: importing pyinfra_cli monkey-patches the whole process with gevent
# (subprocess, threads), which would then leak into every later test of this session.
_LIMIT_GROUPS_SCRIPT = """
import json, sys
from pyinfra.api import State
from pyinfra.context import ctx_state
from pyinfra_cli.inventory import make_inventory_from_files

with ctx_state.use(State()):
    inventory = make_inventory_from_files(sys.argv[1])
members = {group: sorted(host.name for host in inventory.get_group(group))
           for group in ("main", "robot", "team1", "team_2", "jazzy", "humble")}
print(json.dumps({"members": members,
                  "robot_hostname": inventory.get_host("team1-robot").data.ssh_hostname}))
"""


def test_limit_groups_resolve_in_pyinfra():
    # What `--limit` selects from: pyinfra's own inventory built from inventories/lab.py.
    result = subprocess.run(
        [sys.executable, "-c", _LIMIT_GROUPS_SCRIPT, str(REPO / "inventories" / "lab.py")],
        cwd=REPO, env={**os.environ, "ROSLAB_ROSTER": str(FIXTURE)},
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout.splitlines()[-1])
    assert found["members"] == {
        "main": ["team1-main", "team2-main"],
        "robot": ["team1-robot"],
        "team1": ["team1-main", "team1-robot"],
        "team_2": ["team2-main"],
        "jazzy": ["team1-main", "team1-robot"],
        "humble": ["team2-main"],
    }
    assert found["robot_hostname"] == "127.0.0.12"


@pytest.mark.parametrize("command", ["check", "verify", "status", "seed"])
def test_every_roster_command_refuses_a_pyinfra_inventory_in_one_line(command, capsys):
    assert main([command, "inventories/lab.py"] + (["--out", "/nonexistent"] if command == "seed" else [])) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.strip() == (f"roslab {command}: inventories/lab.py is a pyinfra inventory; roslab {command} "
                           f"takes the roster itself (a .yaml file), as every roslab command does: "
                           f"roslab {command} [ROSTER]")


@pytest.mark.parametrize("command", ["check", "verify", "status", "seed"])
def test_every_roster_command_says_a_missing_roster_in_lines_not_a_traceback(command, tmp_path, capsys):
    missing = tmp_path / "classroom.yaml"
    extra = ["--out", str(tmp_path / "out")] if command == "seed" else []
    assert main([command, str(missing), *extra]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"{missing}: cannot read the file: No such file or directory" in err
    assert err.strip().endswith(f"roslab {command}: 1 error in the roster; no host was touched, nothing was written")


@pytest.mark.parametrize("subcommand", [["status"], ["up"], ["down"], ["reset", "team1-main"], ["save", "a"], ["restore", "a"]])
def test_every_sandbox_command_says_it_needs_root_in_one_line(subcommand, monkeypatch, capsys):
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert main(["sandbox", *subcommand]) == 1
    err = capsys.readouterr().err
    assert err.strip() == (f"roslab sandbox {subcommand[0]}: needs root (the sandbox is network namespaces, "
                           "mounts and containers); run it with sudo")


def test_check_shows_an_assigned_domain_id_and_each_teams_mode(tmp_path, capsys):
    from roslab.ros.discovery import preferred_domain_id

    roster = tmp_path / "lab.yaml"
    roster.write_text(textwrap.dedent("""\
        classroom: {ros_discovery_mode: static}
        teams:
          alpha: {ros_domain_id: 5, hosts: {alpha-main: {role: main, address: 10.0.0.1}}}
          bravo: {ros_discovery_mode: discovery_server, hosts: {bravo-main: {role: main, address: 10.0.0.2}}}
    """))
    assert main(["check", str(roster)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:]]
    assert [row[7:-1] for row in rows] == [["5", "static"],
                                        [str(preferred_domain_id("bravo")), "(auto)", "discovery_server"]]


@pytest.mark.parametrize(("limits", "named", "hint"), [
    (["team1,team_2"], "'team1,team_2'", "for several, repeat the option: --limit team1 --limit team_2"),
    (["team1", "tem1"], "'tem1'", "did you mean 'team1'?"),  # one typo among patterns that match
    (["team-2"], "'team-2'", "did you mean 'team_2'?"),  # the group of team-2 is team_2
])
def test_a_pyinfra_limit_that_selects_no_host_stops_the_run_naming_it(limits, named, hint, tmp_path):
    # Real pyinfra, the checkout's inventory: it stops before connecting to any host (the
    # fixture's loopback addresses have no SSH server; a connection attempt would show).
    argv = [str(Path(sys.executable).parent / "pyinfra"), "-y", "inventories/lab.py", "deploy.py"]
    for limit in limits:
        argv += ["--limit", limit]
    result = subprocess.run(argv, cwd=REPO, env={**os.environ, "ROSLAB_ROSTER": str(FIXTURE)},
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stdout + result.stderr
    line = next(line for line in result.stderr.splitlines() if line.startswith("roslab: --limit"))
    assert line.startswith(f"roslab: --limit {named} selects no host of the roster"), line
    assert hint in line and line.endswith("nothing was run"), line
    assert "Connecting" not in result.stdout + result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("command", ["verify", "status"])
def test_roslab_commands_name_a_limit_that_selects_no_host(command, capsys):
    assert main([command, str(FIXTURE), "--limit", "team1", "--limit", "team1,team-2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"roslab {command}: --limit 'team1,team-2' selects no host of the roster"), err
    assert "--limit team1 --limit team-2" in err and "Traceback" not in err


_PYINFRA_LIMIT_SCRIPT = """
import json, sys
from pyinfra.api import State
from pyinfra.context import ctx_state
from pyinfra_cli.cli import _get_inventory_pattern_matches
from pyinfra_cli.inventory import make_inventory_from_files

with ctx_state.use(State()):
    inventory = make_inventory_from_files(sys.argv[1])
print(json.dumps({pattern: sorted(host.name for host in _get_inventory_pattern_matches(inventory, [pattern], "--limit"))
                  for pattern in json.loads(sys.argv[2])}))
"""
LIMIT_PATTERNS = ["team1", "team_2", "team-2", "main", "robot", "jazzy", "humble", "all",
                  "team1-main", "team1-*", "*-main", "team?-*", "nosuch", "team1,team_2"]


def test_every_command_selects_by_limit_what_pyinfras_own_limit_selects():
    from roslab.reach import limit_selection
    from roslab.roster import group_names, load_roster

    result = subprocess.run(
        [sys.executable, "-c", _PYINFRA_LIMIT_SCRIPT, str(REPO / "inventories" / "lab.py"), json.dumps(LIMIT_PATTERNS)],
        cwd=REPO, env={**os.environ, "ROSLAB_ROSTER": str(FIXTURE)}, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    pyinfra_selects = json.loads(result.stdout.splitlines()[-1])
    groups = group_names(load_roster(FIXTURE))
    assert {pattern: sorted(limit_selection(groups, [pattern])[0]) for pattern in LIMIT_PATTERNS} == pyinfra_selects
    assert pyinfra_selects["team-2"] == pyinfra_selects["all"] == [] and len(pyinfra_selects["*-main"]) == 2


def test_trust_seed_and_forget_take_hosts_by_limit_as_every_command_does(tmp_path, capsys):
    from roslab.reach import limited_hosts
    from roslab.roster import load_roster

    classroom = load_roster(FIXTURE)
    names = lambda patterns: [host.name for host in limited_hosts(classroom, patterns, "x")[0]]  # noqa: E731
    assert names(["team_2"]) == ["team2-main"] and names(["robot"]) == ["team1-robot"]
    assert names(["jazzy"]) == names(["team1-*"]) == ["team1-main", "team1-robot"] and len(names(None)) == 3
    hosts, problem = limited_hosts(classroom, ["team1", "team-2"], "roslab x")
    assert hosts == [] and problem.startswith("roslab x: --limit 'team-2' selects no host of the roster")
    assert "did you mean 'team_2'?" in problem

    out = tmp_path / "seeds"
    assert main(["seed", str(FIXTURE), "--out", str(out), "--limit", "nosuch"]) == 2
    assert "roslab seed: --limit 'nosuch' selects no host of the roster" in capsys.readouterr().err
    assert not out.exists()
    for command in ("trust", "forget", "opencr-update", "esp32-firmware"):
        assert main([command, str(FIXTURE), "--limit", "team1,team-2"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"roslab {command}: --limit 'team1,team-2' selects no host of the roster"), err
        assert "--limit team1 --limit team-2" in err and err.count("\n") == 1


@pytest.mark.parametrize(("argv", "shape"), [
    (["forget", "team1-main", "--roster", "R"], "roslab forget R --limit team1-main"),
    (["forget", "team1-main", "team1-robot"], "roslab forget --limit team1-main --limit team1-robot"),
    (["forget", "team1-main"], "roslab forget --limit team1-main"),
    (["opencr-update", "team1-robot", "R"], "roslab opencr-update R --limit team1-robot"),
    (["opencr-update", "team1-robot"], "roslab opencr-update --limit team1-robot"),
    (["opencr-update", "R", "team1-robot"], "roslab opencr-update R --limit team1-robot"),
])
def test_the_older_host_first_form_is_one_line_giving_the_new_one(argv, shape, capsys):
    argv = [str(FIXTURE) if word == "R" else word for word in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == (f"roslab {argv[0]}: hosts are named by --limit, after the roster, as in every roslab "
                   f"command: {shape.replace(' R ', f' {FIXTURE} ').replace(' R', f' {FIXTURE}')}\n")
    # ... and the form it gives is the one the command takes.
    from roslab.cli.main import build_parser
    from roslab.reach import stale_host_form

    args = build_parser().parse_args(shape.replace(" R ", f" {FIXTURE} ").split()[1:])
    assert stale_host_form(args, argv[0]) is None and args.limit == [word for word in argv[1:] if word.startswith("team")]


def test_forget_without_limit_forgets_nothing_and_says_how(tmp_path, capsys):
    roster = tmp_path / "classroom.yaml"
    roster.write_text(FIXTURE.read_text())
    assert main(["forget", str(roster)]) == 2
    assert capsys.readouterr().err == ("roslab forget: name the hosts whose keys to forget with --limit (a team, "
                                       "role, distro or host name): roslab forget [ROSTER] --limit HOST\n")
    assert not (tmp_path / ".roslab-state").exists()


def test_host_is_still_read_as_the_older_name_of_limit_but_only_limit_is_shown(capsys):
    from roslab.cli.main import build_parser

    for command in ("verify", "status", "trust", "seed", "forget", "opencr-update", "esp32-firmware"):
        required = ["--out", "seeds"] if command == "seed" else []
        assert build_parser().parse_args([command, *required, "--host", "team1-main", "--limit", "robot"]).limit == [
            "team1-main", "robot"]
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        shown = capsys.readouterr().out
        assert "--limit NAME" in shown and "--host" not in shown, shown
