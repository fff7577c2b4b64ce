"""rosdep install, colcon build, ownership and the nodes service: facts in, commands out.

Also the classroom accidents the workspace deploy heals on its next run: a workspace given
to root, a node with a syntax error, a nodes unit that gave up.
"""

from __future__ import annotations

import configparser
import grp
import hashlib
import os
import posixpath
import pwd
import re
import shlex
import shutil
import subprocess

import pytest
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra.context import ctx_host

from deploy import workspace as deploy_ws
from roslab import settings
from roslab.ros import workspace
from roslab.ros.environment import host_environment
from fixtures.classroom import typed
from test_workspace_sync import USER, LocalDirHost, run_operation

WS = "/home/ubuntu/ros2_ws"
ARGS = ["--executor", "sequential"]


def stamps(rosdep=None, build=None, installed=True):
    return {workspace.WorkspaceStamps: {"rosdep": rosdep, "build": build, "installed": installed}}


def build_stamp(sources_hash="s1", distro="jazzy", args=ARGS):
    import hashlib

    return hashlib.sha256("\0".join([sources_hash, distro, *args]).encode()).hexdigest()


def build(facts):
    commands, host = run_operation(
        workspace.built, host=LocalDirHost(facts), workspace_dir=WS, distro="jazzy",
        colcon_args=ARGS, sources_hash="s1",
    )
    return [c.get_raw_value() for c in commands], host


def test_build_runs_when_there_is_no_stamp():
    commands, host = build(stamps(build=None, installed=False))
    assert len(commands) == 1 and "colcon build --executor sequential" in commands[0]
    assert host.noops == []


def test_build_is_skipped_when_the_stamp_matches():
    commands, host = build(stamps(build=build_stamp()))
    assert commands == []
    assert host.noops == [f"{WS} is built from these sources already"]


@pytest.mark.parametrize(
    "facts",
    [
        stamps(build=build_stamp(sources_hash="old")),  # a source changed
        stamps(build=build_stamp(distro="humble")),  # another distro
        stamps(build=build_stamp(args=["--parallel-workers", "2"])),  # other colcon args
        stamps(build=build_stamp(), installed=False),  # someone removed install/
    ],
    ids=["sources", "distro", "colcon-args", "install-removed"],
)
def test_build_runs_again_when_anything_it_depends_on_changed(facts):
    commands, _ = build(facts)
    assert len(commands) == 1


def run_build_script(tmp_path, colcon_body: str, python_paths=(), sources=None) -> subprocess.CompletedProcess:
    """Run the build script with fake /opt/ros and colcon, to see what a user would see.

    `sources`: {path relative to the workspace: text} written before the build.
    """
    ws = tmp_path / "ws"
    ws.mkdir()
    for relative, text in (sources or {}).items():
        (ws / relative).parent.mkdir(parents=True, exist_ok=True)
        (ws / relative).write_text(text)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "colcon").write_text(f"#!/bin/sh\ntouch {tmp_path}/colcon-ran\n{colcon_body}\n")
    (bin_dir / "colcon").chmod(0o755)
    script = workspace.build_script(str(ws), "jazzy", ARGS, "stamp-1", python_paths)
    # The script sources /opt/ros/<distro>/setup.bash: point it at a stand-in.
    setup = tmp_path / "setup.bash"
    setup.write_text(f"export PATH={bin_dir}:/usr/bin:/bin\n")
    script = script.replace("/opt/ros/jazzy/setup.bash", str(setup))
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True)


def test_a_successful_build_writes_the_stamp_and_keeps_the_log(tmp_path):
    result = run_build_script(tmp_path, 'echo "Summary: 2 packages finished"')
    assert result.returncode == 0
    ws = tmp_path / "ws"
    assert (ws / ".roslab" / "build.sha256").read_text() == "stamp-1\n"
    assert "2 packages finished" in (ws / "log" / "roslab-build.log").read_text()


def test_a_failed_build_shows_the_logs_tail_and_leaves_no_stamp(tmp_path):
    body = "i=0; while [ $i -lt 100 ]; do echo line $i; i=$((i+1)); done; echo 'SyntaxError: bad'; exit 2"
    (tmp_path / "ws" / ".roslab").mkdir(parents=True)
    (tmp_path / "ws" / ".roslab" / "build.sha256").write_text("stamp-0\n")
    (tmp_path / "ws").rename(tmp_path / "keep")  # run_build_script makes ws itself
    result = run_build_script(tmp_path, body)
    assert result.returncode == 2
    assert "SyntaxError: bad" in result.stderr
    assert "line 99" in result.stderr and "line 50" not in result.stderr
    assert "colcon build failed (exit 2)" in result.stderr
    assert not (tmp_path / "ws" / ".roslab" / "build.sha256").exists()


GOOD_NODE = "def main():\n    print('hello')\n"
BROKEN_NODE = "def main():\n    print('hello'\n\n\ndef other():\n    pass\n"


def test_a_syntax_error_in_a_node_fails_the_build_with_file_and_line_before_colcon(tmp_path):
    result = run_build_script(
        tmp_path, "echo built", python_paths=["src/demo"],
        sources={"src/demo/setup.py": GOOD_NODE, "src/demo/demo/talker.py": BROKEN_NODE,
                 "src/demo/demo/__init__.py": ""},
    )
    assert result.returncode == workspace.SYNTAX_ERROR_EXIT
    ws = tmp_path / "ws"
    # One line naming the file (as it is on the host) and the line of the error.
    (located,) = [line for line in result.stderr.splitlines() if "talker.py" in line]
    assert re.fullmatch(rf"{ws}/src/demo/demo/talker\.py:2: SyntaxError: .+", located), located
    assert "fix the Python file named above" in result.stderr
    assert not (tmp_path / "colcon-ran").exists()  # colcon never ran
    assert not (ws / ".roslab" / "build.sha256").exists()  # so the next run retries
    assert not list(ws.rglob("__pycache__"))  # the check writes no byte-code into src/


def test_every_broken_file_is_named_and_other_packages_are_not_checked(tmp_path):
    result = run_build_script(
        tmp_path, "echo built", python_paths=["src/demo"],
        sources={"src/demo/a.py": "x = (\n", "src/demo/sub/b.py": "\tdef f(:\n",
                 "src/students_own/broken.py": "def (\n"},
    )
    named = [line.split(":")[0] for line in result.stderr.splitlines() if "Error" in line]
    assert named == [f"{tmp_path}/ws/src/demo/a.py", f"{tmp_path}/ws/src/demo/sub/b.py"]


def test_sources_that_compile_go_on_to_colcon(tmp_path):
    result = run_build_script(
        tmp_path, "echo built", python_paths=["src/demo"],
        sources={"src/demo/demo/talker.py": GOOD_NODE, "src/demo/README.md": "not python ("},
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "colcon-ran").exists()
    assert (tmp_path / "ws" / ".roslab" / "build.sha256").read_text() == "stamp-1\n"


def test_the_build_operation_checks_roslabs_packages_only():
    commands, _ = run_operation(
        workspace.built, host=LocalDirHost(stamps()), workspace_dir=WS, distro="jazzy",
        colcon_args=ARGS, sources_hash="s1", python_paths=["src/roslab_bringup", "src/roslab_demo"],
    )
    (command,) = [c.get_raw_value() for c in commands]
    script = shlex.split(command)[2]
    check_line = next(line for line in script.splitlines() if line.startswith("' src/"))
    assert check_line == "' src/roslab_bringup src/roslab_demo; then"


def test_an_interrupted_build_leaves_no_stamp_so_the_next_run_retries(tmp_path):
    # A build killed half way must not leave the stamp of an earlier build behind.
    ws = tmp_path / "ws"
    script = workspace.build_script(str(ws), "jazzy", ARGS, "stamp-2")
    assert script.index("rm -f") < script.index("colcon build")


def test_rosdep_runs_as_root_with_the_users_cache_when_package_xml_changed():
    commands, _ = run_operation(
        workspace.dependencies, host=LocalDirHost(stamps(rosdep="old:jazzy")),
        workspace_dir=WS, packages=["roslab_bringup", "roslab_demo"], distro="jazzy",
        packages_hash="p1", user="ubuntu", ros_home="/home/ubuntu/.ros",
    )
    (command,) = [c.get_raw_value() for c in commands]
    assert (
        "ROS_HOME=/home/ubuntu/.ros rosdep install --from-paths src/roslab_bringup src/roslab_demo"
        " --ignore-src -y" in command
    )
    assert "--rosdistro jazzy" in command
    # The stamp is written as the user (never by root through a link in the user's directory).
    assert command.startswith(f"runuser -u ubuntu -- mkdir -p {WS}/.roslab && ")
    assert command.endswith(
        f"&& runuser -u ubuntu -- sh -c 'printf '\"'\"'%s\\n'\"'\"' p1:jazzy > {WS}/.roslab/rosdep.sha256'"
    )


def test_rosdep_is_skipped_when_no_package_xml_changed():
    commands, host = run_operation(
        workspace.dependencies, host=LocalDirHost(stamps(rosdep="p1:jazzy")),
        workspace_dir=WS, packages=["roslab_demo"], distro="jazzy", packages_hash="p1",
        user="ubuntu", ros_home="/home/ubuntu/.ros",
    )
    assert commands == [] and "already" in host.noops[0]


def test_stamps_fact_reads_a_fresh_workspace_as_unbuilt(tmp_path):
    host = LocalDirHost()
    with ctx_host.use(host):
        assert host.get_fact(workspace.WorkspaceStamps, workspace_dir=str(tmp_path)) == {
            "rosdep": None, "build": None, "installed": False,
        }
    (tmp_path / ".roslab").mkdir()
    (tmp_path / ".roslab" / "build.sha256").write_text("abc\n")
    (tmp_path / "install").mkdir()
    (tmp_path / "install" / "setup.sh").write_text("")
    assert host.get_fact(workspace.WorkspaceStamps, workspace_dir=str(tmp_path)) == {
        "rosdep": None, "build": "abc", "installed": True,
    }


def test_package_xml_hash_ignores_other_files(tmp_path):
    files = {"demo": {"demo/package.xml": workspace.LocalFile("/x", "a", "644"),
                      "demo/setup.py": workspace.LocalFile("/y", "b", "644")}}
    edited = {"demo": {**files["demo"], "demo/setup.py": workspace.LocalFile("/y", "c", "644")}}
    assert workspace.tree_hash(files, only="package.xml") == workspace.tree_hash(edited, only="package.xml")
    assert workspace.tree_hash(files) != workspace.tree_hash(edited)


def test_restart_forgets_earlier_failures_first():
    commands, _ = run_operation(workspace.restarted, service="roslab-nodes.service")
    assert [str(c) for c in commands] == [
        "systemctl reset-failed roslab-nodes.service 2>/dev/null; systemctl restart roslab-nodes.service"
    ]


# Ownership: a workspace a student gave to root
# ---------------------------------------------


def test_ownership_fact_reads_paths_of_others_and_a_missing_workspace_as_none(tmp_path):
    host = LocalDirHost()
    with ctx_host.use(host):
        group = grp.getgrgid(pwd.getpwnam(USER).pw_gid).gr_name
        fact = dict(workspace_dir=str(tmp_path / "missing"), user=USER)
        # no workspace yet: nothing foreign, and the group its folders are created with
        assert host.get_fact(workspace.WorkspaceForeign, **fact) == {"count": 0, "examples": [], "group": group}
        ws = tmp_path / "ws"
        (ws / "build" / "demo").mkdir(parents=True)
        (ws / "log").mkdir()
        fact = dict(workspace_dir=str(ws), user=USER)
        assert host.get_fact(workspace.WorkspaceForeign, **fact) == {"count": 0, "examples": [], "group": group}
        if os.geteuid() != 0:
            pytest.skip("giving files to another user needs root")
        for path in (ws / "build", ws / "build" / "demo", ws / "log"):
            os.chown(path, 0, 0)
        other = "nobody" if USER == "root" else USER
        foreign = host.get_fact(workspace.WorkspaceForeign, workspace_dir=str(ws), user=other)
    # every path (the workspace itself too, when it is root's): counted, a few named
    assert foreign["count"] >= 3 and len(foreign["examples"]) == workspace.FOREIGN_EXAMPLES


def test_ownership_fact_output_is_parsed():
    fact = workspace.WorkspaceForeign()
    assert fact.process(["group ubuntu", "path build", "path ", "path log/latest", "count 1234"]) == {
        "count": 1234, "examples": ["build", ".", "log/latest"], "group": "ubuntu",
    }
    assert fact.process(["group ubuntu"]) == {"count": 0, "examples": [], "group": "ubuntu"}
    assert fact.process([]) == {"count": 0, "examples": [], "group": None}  # no such user


def test_a_workspace_given_to_root_is_given_back_whole():
    foreign = {workspace.WorkspaceForeign: {"count": 812, "examples": ["build", "build/demo", "install"]}}
    commands, _ = run_operation(workspace.owned, host=LocalDirHost(foreign), workspace_dir=WS, user="ubuntu")
    assert [c.get_raw_value() for c in commands] == [f"chown -R -- ubuntu: {WS}"]


def test_a_workspace_that_belongs_to_its_user_is_left_alone():
    commands, host = run_operation(
        workspace.owned, host=LocalDirHost({workspace.WorkspaceForeign: {"count": 0, "examples": []}}),
        workspace_dir=WS, user="ubuntu",
    )
    assert commands == [] and host.noops == [f"everything in {WS} belongs to ubuntu"]


def test_chown_gives_back_the_whole_tree_without_following_links(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("giving files to another user needs root")
    ws = tmp_path / "ws"
    (ws / "install" / "demo").mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.write_text("not the workspace's")
    (ws / "install" / "link").symlink_to(outside)
    for path in (ws, ws / "install", ws / "install" / "demo"):
        os.chown(path, 0, 0)
    os.chown(outside, 0, 0)
    commands, _ = run_operation(
        workspace.owned, host=LocalDirHost({workspace.WorkspaceForeign: {"count": 3, "examples": []}}),
        workspace_dir=str(ws), user="nobody",
    )
    subprocess.run(["sh", "-c", commands[0].get_raw_value()], check=True)

    nobody = pwd.getpwnam("nobody").pw_uid
    assert {p.lstat().st_uid for p in [ws, *ws.rglob("*")]} == {nobody}
    assert outside.stat().st_uid == 0  # the link changed owner, not its target


# The nodes unit: its state, and a unit that gave up
# --------------------------------------------------


def test_unit_state_fact_asks_about_this_unit_only():
    fact = workspace.NodesUnitState()
    command = fact.command(service="roslab-nodes.service")
    assert command == ("systemctl show --property=LoadState,ActiveState,SubState,Result "
                       "roslab-nodes.service")
    assert "--all" not in command
    assert fact.process(["LoadState=loaded", "ActiveState=failed", "SubState=failed",
                         "Result=start-limit-hit"]) == {
        "LoadState": "loaded", "ActiveState": "failed", "SubState": "failed", "Result": "start-limit-hit",
    }


@pytest.mark.parametrize(
    ("state", "reason"),
    [
        (("loaded", "active", "running", "success"), None),
        (("loaded", "activating", "auto-restart", "exit-code"), None),  # systemd is still trying
        (("loaded", "failed", "failed", "start-limit-hit"), "failed (start-limit-hit)"),
        (("loaded", "failed", "failed", "exit-code"), "failed (exit-code)"),
        (("loaded", "inactive", "dead", "success"), "inactive (stopped)"),
        (("not-found", "inactive", "dead", "success"), None),  # not installed yet
    ],
)
def test_a_unit_that_gave_up_or_was_stopped_needs_a_start(state, reason):
    keys = ("LoadState", "ActiveState", "SubState", "Result")
    assert workspace.stopped_reason(dict(zip(keys, state))) == reason


# The unit file
# -------------


def render_unit(**overrides) -> str:
    variables = dict(
        role="robot", user="ubuntu", home="/home/ubuntu", workspace_dir=WS, distro="jazzy",
        launch="roslab_bringup robot.launch.py",
        environment={"ROS_DOMAIN_ID": "11", "ROS_STATIC_PEERS": "10.0.0.1;10.0.0.2"},
    )
    variables.update(overrides)
    return deploy_ws.unit_text(**variables)


def parse_unit(text: str) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None, delimiters=("=",))
    parser.optionxform = str
    parser.read_string(text)
    return parser


C_ESCAPES = {"a": "\a", "b": "\b", "f": "\f", "n": "\n", "r": "\r", "t": "\t", "v": "\v",
             "\\": "\\", '"': '"', "'": "'", "s": " "}


def systemd_exec_argv(value: str) -> list[str]:
    """An ExecStart= value as systemd turns it into argv (systemd.service(5), "Command lines").

    Specifiers first (only %% may be left: it is one %), then words with quotes and C
    escapes, then environment variables (only $$ may be left: it is one $). A reference
    written from the documentation, independent of roslab.quoting.
    """
    text = ""
    i = 0
    while i < len(value):
        if value[i] == "%":
            assert value[i + 1] == "%", f"systemd would expand the specifier %{value[i + 1]}"
            text, i = text + "%", i + 2
        else:
            text, i = text + value[i], i + 1
    words, word, quote, in_word, i = [], "", None, False, 0
    while i < len(text):
        char = text[i]
        if char == "\\":
            following = text[i + 1]
            if following == "x":
                word, i = word + chr(int(text[i + 2:i + 4], 16)), i + 4
            else:
                word, i = word + C_ESCAPES[following], i + 2
            in_word = True
            continue
        if quote:
            if char == quote:
                quote = None
            else:
                word += char
        elif char in "\"'":
            quote, in_word = char, True
        elif char.isspace():
            if in_word:
                words.append(word)
            word, in_word = "", False
        else:
            word, in_word = word + char, True
        i += 1
    assert quote is None, "unterminated quote"
    if in_word:
        words.append(word)
    argv = []
    for word in words:
        out, i = "", 0
        while i < len(word):
            if word[i] == "$":
                assert word[i + 1] == "$", f"systemd would expand ${word[i + 1:]}"
                out, i = out + "$", i + 2
            else:
                out, i = out + word[i], i + 1
        argv.append(out)
    return argv


def test_unit_runs_the_roles_launch_as_the_user_after_the_network():
    text = render_unit()
    assert text.startswith("# managed by roslab")
    unit = parse_unit(text)
    assert unit["Unit"]["After"] == "network-online.target"
    assert unit["Unit"]["Wants"] == "network-online.target"
    assert unit["Unit"]["Description"] == "roslab robot nodes (ros2 launch roslab_bringup robot.launch.py)"
    assert unit["Service"]["User"] == "ubuntu"
    assert unit["Service"]["Restart"] == "always"
    assert unit["Install"]["WantedBy"] == "multi-user.target"
    assert systemd_exec_argv(unit["Service"]["ExecStart"]) == [
        "/bin/bash", "-c",
        "source /opt/ros/jazzy/setup.bash && source /home/ubuntu/ros2_ws/install/setup.bash && "
        "exec ros2 launch roslab_bringup robot.launch.py",
    ]


HOSTILE_HOME = "/home/o'neil \"quoted\" 100%h $USER ${HOME} \\x27 back\\slash"


def test_unit_writes_a_hostile_home_so_systemd_and_bash_read_it_back_exactly():
    """%, $, C escapes, quotes and spaces in the home (the host's value, not the roster's)."""
    workspace_dir = HOSTILE_HOME + "/ros2_ws"
    unit = parse_unit(render_unit(home=HOSTILE_HOME, workspace_dir=workspace_dir))
    argv = systemd_exec_argv(unit["Service"]["ExecStart"])
    assert argv[:2] == ["/bin/bash", "-c"]
    script = argv[2]
    assert script == deploy_ws.exec_script(
        distro="jazzy", workspace_dir=workspace_dir, launch="roslab_bringup robot.launch.py")
    # ... and bash reads the workspace's setup.bash path back as the home's exact text.
    words = shlex.split(script)
    assert words[words.index("&&") - 1] == "/opt/ros/jazzy/setup.bash"
    assert f"{workspace_dir}/install/setup.bash" in words
    # WorkingDirectory= takes the path as it is, with % doubled (specifiers).
    assert unit["Service"]["WorkingDirectory"].replace("%%", "%") == HOSTILE_HOME


def test_the_exec_script_runs_in_bash_exactly_as_written(tmp_path):
    """The script systemd hands bash sources the hostile path and execs the launch, nothing else."""
    home = tmp_path / "o'neil $(touch pwned) %h \\x27"
    setup = home / "ros2_ws" / "install" / "setup.bash"
    setup.parent.mkdir(parents=True)
    setup.write_text("echo workspace sourced\n")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "ros2").write_text('#!/bin/sh\necho "ros2 $*"\n')
    (bin_dir / "ros2").chmod(0o755)
    distro_setup = tmp_path / "distro.bash"
    distro_setup.write_text(f"export PATH={bin_dir}:/usr/bin:/bin\n")
    unit = parse_unit(render_unit(home=str(home), workspace_dir=f"{home}/ros2_ws"))
    script = systemd_exec_argv(unit["Service"]["ExecStart"])[2]
    script = script.replace("/opt/ros/jazzy/setup.bash", shlex.quote(str(distro_setup)))
    ran = subprocess.run(["bash", "-c", script], capture_output=True, text=True, cwd=tmp_path)
    assert ran.stdout == "workspace sourced\nros2 launch roslab_bringup robot.launch.py\n", ran.stderr
    assert not list(tmp_path.rglob("pwned"))


def test_unit_environment_lines_are_quoted_for_systemd():
    lines = [line for line in render_unit().splitlines() if line.startswith("Environment=")]
    assert lines == [
        'Environment="ROS_DOMAIN_ID=11"',
        'Environment="ROS_STATIC_PEERS=10.0.0.1;10.0.0.2"',
    ]
    (line,) = [line for line in render_unit(environment={"A": '50% "x" $y'}).splitlines()
               if line.startswith("Environment=")]
    assert line == 'Environment="A=50%% \\"x\\" $y"'


def test_a_value_with_a_newline_cannot_reach_the_unit():
    with pytest.raises(ValueError, match="single line"):
        render_unit(home="/home/x\nExecStartPre=/bin/rm -rf /")
    with pytest.raises(ValueError, match="single line"):
        render_unit(environment={"ROS_STATIC_PEERS": "a\nExecStartPre=/bin/true"})


def test_unit_has_no_blank_lines_left_by_the_template_loop():
    assert "\n\n\n" not in render_unit()
    assert "\n\nExecStart" not in render_unit()


def test_unit_is_valid_for_systemd(tmp_path):
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    for name, text in [("plain", render_unit(user="root", home="/root")),
                       ("hostile", render_unit(user="root", home="/root",
                                               workspace_dir=HOSTILE_HOME + "/ros2_ws"))]:
        unit = tmp_path / name / "roslab-nodes.service"
        unit.parent.mkdir()
        unit.write_text(text)
        result = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True)
        # Any complaint about the unit file itself (unknown keys, bad quoting) names its path.
        problems = [line for line in result.stderr.splitlines() if str(unit) in line]
        assert problems == [], name


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
@pytest.mark.parametrize(
    "values",
    [
        dict(ros_domain_id=11, ros_automatic_discovery_range="SUBNET", ros_static_peers=[]),
        dict(ros_domain_id=0, ros_automatic_discovery_range="LOCALHOST", ros_static_peers=[]),
        dict(ros_domain_id=42, ros_automatic_discovery_range="OFF",
             ros_static_peers=["10.0.0.2", "team1-robot"]),
    ],
)
def test_service_environment_is_what_the_bashrc_block_exports(distro, values):
    from deploy.shell_env import render_ros_environment

    data = {"ros_discovery_mode": "multicast", **values}
    block = render_ros_environment(distro, host_environment(typed(data), distro, shell=True))
    exported = {}
    for line in block.splitlines():
        if line.startswith("export ") and not line.startswith("export ROSDISTRO_INDEX_URL"):
            name, _, value = line[len("export "):].partition("=")
            exported[name] = shlex.split(value)[0]
    environment = host_environment(typed(data), distro)
    unit = render_unit(distro=distro, environment=environment)
    in_unit = dict(shlex.split(line.removeprefix("Environment="))[0].split("=", 1)
                   for line in unit.splitlines() if line.startswith("Environment="))
    assert in_unit == exported


# The deploy on a fake host: facts in, commands out
# -------------------------------------------------

NODES = deploy_ws.REPO / "nodes"
STUDENT_WS = "/home/student/ros2_ws"
HEALTHY = {"LoadState": "loaded", "ActiveState": "active", "SubState": "running", "Result": "success"}


def host_data(**more) -> dict:
    """Host data as the roster loader gives it: every default, then the host's values."""
    return {**settings.defaults(), "ssh_user": "student", "roslab_team": "team1",
            "roslab_role": "robot", "roslab_hostname": "team1-robot", "ros_domain_id": 11, **more}


def synced(nodes_dir, user="student") -> dict:
    """The WorkspacePackages fact of a src/ that holds exactly nodes_dir's packages."""
    local = workspace.local_packages(nodes_dir)
    entries = {}
    for package, files in local.items():
        for relative, local_file in files.items():
            entries[relative] = workspace.RemoteEntry("f", local_file.mode, user, user, local_file.sha256)
            parent = posixpath.dirname(relative)
            while parent:
                entries[parent] = workspace.RemoteEntry("d", "755", user, user)
                parent = posixpath.dirname(parent)
    return {"manifest": sorted(local), "group": user, "entries": entries}


class WorkspaceHost(FakeUbuntu):
    """FakeUbuntu with the workspace's facts: fresh, or as a finished first run left it."""

    def __init__(self, converged: bool = False, nodes_dir=NODES, facts: dict | None = None):
        super().__init__("noble")
        self.workspace_facts = {
            workspace.WorkspacePackages: {},
            workspace.WorkspaceStamps: {"rosdep": None, "build": None, "installed": False},
            workspace.WorkspaceForeign: self._foreign,
            workspace.NodesUnitState: {"LoadState": "not-found", "ActiveState": "inactive",
                                       "SubState": "dead", "Result": "success"},
        }
        if converged:
            local = workspace.local_packages(nodes_dir)
            managed = [f"src/{name}" for name in sorted(local)]
            colcon_args = [*settings.defaults()["workspace_colcon_args"], "--paths", *managed]
            build_stamp = hashlib.sha256(
                "\0".join([workspace.tree_hash(local), "jazzy", *colcon_args]).encode()).hexdigest()
            self.workspace_facts.update({
                workspace.WorkspacePackages: synced(nodes_dir),
                workspace.WorkspaceStamps: {
                    "rosdep": workspace.tree_hash(local, only="package.xml") + ":jazzy",
                    "build": build_stamp, "installed": True,
                },
                workspace.NodesUnitState: dict(HEALTHY),
            })
            for path in (STUDENT_WS, STUDENT_WS + "/src"):
                self.dirs[path] = ("student", "student", 755)
            self.dirs["/etc/systemd/system"] = ("root", "root", 755)
            self.enabled_units[workspace.NODES_SERVICE] = True
            unit_text = deploy_ws.unit_text(
                role="robot", user="student", home="/home/student", workspace_dir=STUDENT_WS,
                distro="jazzy", launch="roslab_bringup robot.launch.py",
                environment=host_environment(typed(host_data()), "jazzy"))
            self.files[workspace.NODES_UNIT_PATH] = unit_text.splitlines()
            self.raw[workspace.NODES_UNIT_PATH] = unit_text
        self.workspace_facts.update(facts or {})

    def facts(self) -> dict:
        return {**super().facts(), **self.workspace_facts}

    def _foreign(self, workspace_dir: str, user: str) -> dict:
        """WorkspaceForeign as the host's folders give it (the user's group is named as the user)."""
        foreign = sorted(posixpath.relpath(path, workspace_dir) for path, (owner, group, _) in self.dirs.items()
                         if (path + "/").startswith(workspace_dir + "/") and (owner, group) != (user, user))
        return {"count": len(foreign), "examples": foreign[:workspace.FOREIGN_EXAMPLES], "group": user}


def run_workspace(host: WorkspaceHost, **data):
    return plan(deploy_ws.workspace, host.facts(), host_data(**data))


def changes(result) -> dict[str, list[str]]:
    """Operation name (without the deploy's) -> commands, for what would change."""
    return {name.split(" | ")[-1]: commands for name, commands in result.changing().items()}


def test_a_fresh_host_gets_every_step_as_the_login_user():
    result = run_workspace(WorkspaceHost())
    assert not result.failed, result.errors
    assert any("exists, owned by student" in name for name in changes(result))
    build = result.operation("is built from these sources")
    assert build.arguments.get("_sudo_user") == "student"
    (script,) = build.text()
    assert "src/roslab_bringup src/roslab_demo src/roslab_esp32; then" in script  # the syntax check, then colcon
    assert result.operation("runs the current build and unit").text() == [
        "systemctl reset-failed roslab-nodes.service 2>/dev/null; systemctl restart roslab-nodes.service"
    ]
    unit = result.uploads()[workspace.NODES_UNIT_PATH]
    assert "User=student" in unit and 'Environment="ROS_DOMAIN_ID=11"' in unit


def test_a_converged_healthy_host_changes_nothing():
    result = run_workspace(WorkspaceHost(converged=True))
    assert not result.failed, result.errors
    assert changes(result) == {}


def test_a_fresh_workspace_gets_the_users_group_so_the_next_run_gives_nothing_back(caplog):
    host = WorkspaceHost()
    first = run_workspace(host)
    for path in (STUDENT_WS, STUDENT_WS + "/src"):
        assert changes(first)[f"Ensure {path} exists, owned by student"] == [
            f"mkdir -p {path}", f"chown student:student {path}"]
    host.apply(first)
    with caplog.at_level("WARNING", logger="pyinfra"):
        second = run_workspace(host)
    assert f"Ensure everything in {STUDENT_WS} belongs to student" not in changes(second)
    assert not [r for r in caplog.records if "not belong" in r.getMessage()]


def test_a_students_sudo_build_is_given_back_and_said(caplog):
    host = WorkspaceHost(converged=True)
    host.dirs[STUDENT_WS + "/build"] = ("root", "root", 755)  # `sudo colcon build`
    with caplog.at_level("WARNING", logger="pyinfra"):
        result = run_workspace(host)
    assert list(changes(result)) == [f"Ensure everything in {STUDENT_WS} belongs to student"]
    (line,) = [r.getMessage() for r in caplog.records if "not belong" in r.getMessage()]
    assert "1 path in /home/student/ros2_ws does not belong to student (build): giving" in line


def test_a_workspace_given_to_root_is_the_one_change_and_is_named_for_its_host(caplog):
    foreign = {"count": 2046, "examples": [".", "build", "build/roslab_demo"], "group": "student"}
    host = WorkspaceHost(converged=True, facts={workspace.WorkspaceForeign: foreign})
    with caplog.at_level("WARNING", logger="pyinfra"):
        result = run_workspace(host)
    assert changes(result) == {
        f"Ensure everything in {STUDENT_WS} belongs to student": [f"chown -R -- student: {STUDENT_WS}"],
    }
    (line,) = [" ".join(r.getMessage().split()) for r in caplog.records if "do not belong" in r.getMessage()]
    assert line.startswith("[pi] workspace: 2046 paths in /home/student/ros2_ws do not belong to student")


@pytest.mark.parametrize(
    ("state", "said"),
    [
        ({"ActiveState": "failed", "SubState": "failed", "Result": "start-limit-hit"},
         "roslab-nodes.service is failed (start-limit-hit): starting it again"),
        ({"ActiveState": "inactive", "SubState": "dead", "Result": "success"},
         "roslab-nodes.service is inactive (stopped): starting it again"),
    ],
)
def test_a_unit_that_gave_up_or_was_stopped_is_started_again_and_said_so(caplog, state, said):
    host = WorkspaceHost(converged=True, facts={workspace.NodesUnitState: {"LoadState": "loaded", **state}})
    with caplog.at_level("WARNING", logger="pyinfra"):
        result = run_workspace(host)
    assert changes(result) == {
        "Ensure roslab-nodes.service runs the current build and unit": [
            "systemctl reset-failed roslab-nodes.service 2>/dev/null; systemctl restart roslab-nodes.service"
        ],
    }
    said_lines = [" ".join(r.getMessage().split()) for r in caplog.records if "starting it again" in r.getMessage()]
    assert said_lines == [f"[pi] workspace: {said}"]


def test_a_unit_systemd_is_still_restarting_is_left_to_systemd():
    state = {"LoadState": "loaded", "ActiveState": "activating", "SubState": "auto-restart", "Result": "exit-code"}
    result = run_workspace(WorkspaceHost(converged=True, facts={workspace.NodesUnitState: state}))
    assert changes(result) == {}


def test_a_missing_login_user_stops_that_host_before_any_change():
    result = run_workspace(WorkspaceHost(), login_user="ghost")
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi (team team1)" in error and "login_user 'ghost' does not exist" in error


def test_a_nodes_dir_without_packages_stops_that_host_only(tmp_path):
    result = run_workspace(WorkspaceHost(), workspace_nodes_dir=str(tmp_path))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi (team team1): workspace:" in error and "holds no ROS packages" in error


def test_the_workspace_dir_setting_is_the_login_users_home_path():
    assert workspace.workspace_path("/home/u", "~/ros2_ws") == "/home/u/ros2_ws"
    assert workspace.workspace_path("/home/u", "~/labs/ws.v2/") == "/home/u/labs/ws.v2"
    # The schema refuses what could leave the home or run in a shell.
    check = settings.SETTINGS["workspace_dir"]
    for bad in ["ros2_ws", "/opt/ws", "~/../root", "~/$(touch x)", "~/a b", "~/x\ny"]:
        assert settings.check_value(check, bad), bad


def test_with_the_service_off_an_installed_unit_is_stopped_and_disabled():
    host = WorkspaceHost(converged=True)
    result = run_workspace(host, nodes_service_enabled=False)
    assert any("is stopped and disabled" in name for name in changes(result))
    assert not any("runs the current build" in op.name for op in result.operations)


def test_default_nodes_dir_is_the_checkouts_nodes():
    from fixtures.fake_host import fake_host

    with fake_host({}, {"workspace_nodes_dir": None}):
        assert deploy_ws.nodes_dir() == str(deploy_ws.REPO / "nodes")


# The real colcon (where installed), on a workspace the sync operation filled
# ----------------------------------------------------------------------------


def test_synced_workspace_builds_with_real_colcon_and_rebuilds_only_on_change(tmp_path):
    """nodes/ -> src/ with the sync operation, then the build script with this machine's colcon.

    /opt/ros/<distro>/setup.bash is a stand-in here (no ROS runtime on this machine), so
    the console scripts are built and installed but running one stops at `import rclpy`.
    """
    from test_nodes_build import require_colcon

    require_colcon()  # skips on a developer's machine without colcon; fails in CI
    from test_workspace_sync import apply_locally

    ws = tmp_path / "ros2_ws"
    (ws / "src").mkdir(parents=True)
    commands, _ = run_operation(
        workspace.packages, nodes_dir=str(deploy_ws.REPO / "nodes"), src_dir=str(ws / "src"),
        user=USER,
    )
    apply_locally(commands)
    stand_in_setup = tmp_path / "setup.bash"
    stand_in_setup.write_text("# stand-in for /opt/ros/jazzy/setup.bash: no ROS runtime here\n")

    def build_commands():
        packages = workspace.local_packages(ws / "src")
        commands, _ = run_operation(
            workspace.built, workspace_dir=str(ws), distro="jazzy",
            colcon_args=[*ARGS, "--paths", *(f"src/{name}" for name in sorted(packages))],
            sources_hash=workspace.tree_hash(packages),
            python_paths=[f"src/{name}" for name in sorted(packages)],
        )
        return [c.get_raw_value().replace("/opt/ros/jazzy/setup.bash", str(stand_in_setup))
                for c in commands]

    (command,) = build_commands()
    result = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr

    talker = ws / "install" / "roslab_demo" / "lib" / "roslab_demo" / "talker"
    assert os.access(talker, os.X_OK)
    assert "Summary: 3 packages finished" in (ws / "log" / "roslab-build.log").read_text()
    assert os.access(ws / "install" / "roslab_esp32" / "lib" / "roslab_esp32" / "servo_follower", os.X_OK)
    assert build_commands() == []  # built from these sources already

    # As `ros2 run roslab_demo talker` would: with the workspace's environment.
    ran = subprocess.run(
        ["bash", "-c", f"source {ws}/install/setup.bash && {talker}"],
        capture_output=True, text=True, timeout=60,
    )
    assert "ModuleNotFoundError: No module named 'rclpy'" in ran.stderr

    # A syntax error in a node: named with its line before colcon runs, and retried.
    talker_py = ws / "src" / "roslab_demo" / "roslab_demo" / "talker.py"
    good_talker = talker_py.read_text()
    talker_py.write_text(good_talker + "\ndef broken(:\n")
    (command,) = build_commands()
    result = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=300)
    assert result.returncode == workspace.SYNTAX_ERROR_EXIT
    line = len(good_talker.splitlines()) + 2
    assert f"{talker_py}:{line}: SyntaxError:" in result.stderr
    assert "colcon build failed" not in result.stderr
    assert len(build_commands()) == 1

    # A package colcon cannot build: the build fails, its log's tail is the error, and it is retried.
    talker_py.write_text(good_talker)
    setup_py = ws / "src" / "roslab_demo" / "setup.py"
    setup_py.write_text(setup_py.read_text() + "\nraise RuntimeError('this package cannot be built')\n")
    (command,) = build_commands()
    result = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    assert "colcon build failed" in result.stderr and "roslab_demo" in result.stderr
    assert len(build_commands()) == 1
