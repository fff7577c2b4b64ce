"""rosdep install, colcon build and the nodes service: facts in, commands out."""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import pytest
from pyinfra.api import DeployError
from pyinfra.api.util import get_template
from pyinfra.context import ctx_host

from deploy import workspace as deploy_ws
from roslab import workspace
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


def run_build_script(tmp_path, colcon_body: str) -> subprocess.CompletedProcess:
    """Run the build script with fake /opt/ros and colcon, to see what a user would see."""
    ws = tmp_path / "ws"
    ws.mkdir()
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "colcon").write_text(f"#!/bin/sh\n{colcon_body}\n")
    (bin_dir / "colcon").chmod(0o755)
    script = workspace.build_script(str(ws), "jazzy", ARGS, "stamp-1")
    # The script sources /opt/ros/<distro>/setup.bash: point it at a stand-in.
    setup = tmp_path / "setup.bash"
    setup.write_text(f"export PATH={bin_dir}:$PATH\n")
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
    assert command.endswith(
        f"printf '%s\\n' p1:jazzy > {WS}/.roslab/rosdep.sha256 && chown ubuntu: {WS}/.roslab/rosdep.sha256"
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


# The unit
# --------


def render_unit(**overrides) -> str:
    variables = dict(
        role="robot", user="ubuntu", home="/home/ubuntu", workspace_dir=WS, distro="jazzy",
        launch=("roslab_bringup", "robot.launch.py"),
        environment={"ROS_DOMAIN_ID": "11", "ROS_STATIC_PEERS": "10.0.0.1;10.0.0.2"},
    )
    variables.update(overrides)
    template = get_template(str(deploy_ws.TEMPLATES / "roslab-nodes.service.j2"), deploy_ws.JINJA_ENV)
    return template.render(deploy_ws.unit_variables(**variables))


def parse_unit(text: str) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None, delimiters=("=",))
    parser.optionxform = str
    parser.read_string(text)
    return parser


def test_unit_runs_the_roles_launch_as_the_user_after_the_network():
    text = render_unit()
    assert text.startswith("# managed by roslab")
    unit = parse_unit(text)
    assert unit["Unit"]["After"] == "network-online.target"
    assert unit["Unit"]["Wants"] == "network-online.target"
    assert unit["Service"]["User"] == "ubuntu"
    assert unit["Service"]["Restart"] == "on-failure"
    assert unit["Install"]["WantedBy"] == "multi-user.target"
    assert unit["Service"]["ExecStart"] == (
        "/bin/bash -c 'source /opt/ros/jazzy/setup.bash && "
        "source /home/ubuntu/ros2_ws/install/setup.bash && "
        "exec ros2 launch roslab_bringup robot.launch.py'"
    )


def test_unit_environment_lines_are_quoted_for_systemd():
    lines = [line for line in render_unit().splitlines() if line.startswith("Environment=")]
    assert lines == [
        'Environment="ROS_DOMAIN_ID=11"',
        'Environment="ROS_STATIC_PEERS=10.0.0.1;10.0.0.2"',
    ]
    assert deploy_ws.systemd_environment({"A": '50% "x"'}) == ['"A=50%% \\"x\\""']


def test_unit_has_no_blank_lines_left_by_the_template_loop():
    assert "\n\n\n" not in render_unit()
    assert "\n\nExecStart" not in render_unit()


def test_unit_is_valid_for_systemd(tmp_path):
    verify = subprocess.run(["which", "systemd-analyze"], capture_output=True)
    if verify.returncode:
        pytest.skip("systemd-analyze is not installed")
    unit = tmp_path / "roslab-nodes.service"
    unit.write_text(render_unit(user="root", home="/root"))
    result = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True
    )
    # Any complaint about the unit file itself (unknown keys, bad quoting) names its path.
    problems = [line for line in result.stderr.splitlines() if str(unit) in line]
    assert problems == []


# Settings checks
# ---------------


def with_data(**data):
    fake = LocalDirHost()
    fake.name = "team1-robot"
    fake.data = SimpleNamespace(**data, get=lambda key, default=None: data.get(key, default))
    return ctx_host.use(fake)


def test_launch_setting_must_name_package_and_file():
    with with_data(roslab_team="team1", nodes_launch_robot="roslab_bringup"):
        with pytest.raises(DeployError, match="team1-robot.*team1.*nodes_launch_robot"):
            deploy_ws.launch_for("robot")
    with with_data(roslab_team="team1", nodes_launch_robot="roslab_bringup robot.launch.py"):
        assert deploy_ws.launch_for("robot") == ("roslab_bringup", "robot.launch.py")


def test_workspace_dir_expands_home_and_rejects_relative_paths():
    with with_data(workspace_dir="~/ros2_ws"):
        assert deploy_ws.workspace_path("/home/ubuntu") == "/home/ubuntu/ros2_ws"
    with with_data(workspace_dir="ros2_ws", roslab_team="team1"):
        with pytest.raises(DeployError, match="workspace_dir 'ros2_ws' must be absolute"):
            deploy_ws.workspace_path("/home/ubuntu")


def test_colcon_args_must_be_a_list():
    with with_data(workspace_colcon_args="--executor sequential", roslab_team="t"):
        with pytest.raises(DeployError, match="workspace_colcon_args must be a list"):
            deploy_ws.colcon_args()


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
@pytest.mark.parametrize(
    "settings",
    [
        dict(ros_domain_id=11, ros_automatic_discovery_range="SUBNET", ros_static_peers=[]),
        dict(ros_domain_id=0, ros_automatic_discovery_range="LOCALHOST", ros_static_peers=[]),
        dict(ros_domain_id=42, ros_automatic_discovery_range="OFF",
             ros_static_peers=["10.0.0.2", "team1-robot"]),
    ],
)
def test_service_environment_is_what_the_bashrc_block_exports(distro, settings):
    from deploy import shell_env

    block = shell_env.render_ros_environment(
        distro=distro,
        domain_id=settings["ros_domain_id"],
        discovery_range=settings["ros_automatic_discovery_range"],
        static_peers=settings["ros_static_peers"],
    )
    exported = {}
    for line in block.splitlines():
        if line.startswith("export ") and not line.startswith("export ROSDISTRO_INDEX_URL"):
            name, _, value = line[len("export "):].partition("=")
            exported[name] = value.strip("'")
    with with_data(**settings):
        assert deploy_ws.ros_environment(distro) == exported


def test_default_nodes_dir_is_the_checkouts_nodes():
    with with_data(workspace_nodes_dir=None):
        assert Path(deploy_ws.nodes_dir()) == deploy_ws.REPO / "nodes"


# The real colcon (where installed), on a workspace the sync operation filled
# ----------------------------------------------------------------------------


@pytest.mark.skipif(shutil.which("colcon") is None, reason="colcon is not installed")
def test_synced_workspace_builds_with_real_colcon_and_rebuilds_only_on_change(tmp_path):
    """nodes/ -> src/ with the sync operation, then the build script with this machine's colcon.

    /opt/ros/<distro>/setup.bash is a stand-in here (no ROS runtime on this machine), so
    the console scripts are built and installed but running one stops at `import rclpy`.
    """
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
        )
        return [c.get_raw_value().replace("/opt/ros/jazzy/setup.bash", str(stand_in_setup))
                for c in commands]

    (command,) = build_commands()
    result = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr

    talker = ws / "install" / "roslab_demo" / "lib" / "roslab_demo" / "talker"
    assert os.access(talker, os.X_OK)
    assert "Summary: 2 packages finished" in (ws / "log" / "roslab-build.log").read_text()
    assert build_commands() == []  # built from these sources already

    # As `ros2 run roslab_demo talker` would: with the workspace's environment.
    ran = subprocess.run(
        ["bash", "-c", f"source {ws}/install/setup.bash && {talker}"],
        capture_output=True, text=True, timeout=60,
    )
    assert "ModuleNotFoundError: No module named 'rclpy'" in ran.stderr

    # A broken setup.py: the build fails, its log's tail is the error, and it is retried.
    (ws / "src" / "roslab_demo" / "setup.py").write_text("from setuptools import setup\nsetup(\n")
    (command,) = build_commands()
    result = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    assert "colcon build failed" in result.stderr and "roslab_demo" in result.stderr
    assert len(build_commands()) == 1
