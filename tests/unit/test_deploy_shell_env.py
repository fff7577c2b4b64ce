"""The ~/.bashrc block: what a student's shell gets on each distro, and that it runs no value."""

from __future__ import annotations

import subprocess

import pytest
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy.shell_env import render_ros_environment as render_block, shell_env
from roslab import settings
from roslab.ros.environment import host_environment
from fixtures.classroom import typed


def ros_variables(distro: str, domain_id: int, discovery_range: str = "SUBNET", static_peers=()) -> dict:
    """A host's variables for these settings, in multicast discovery (where the range and the
    peers are the roster's own), as the deploy computes them."""
    data = {"ros_domain_id": domain_id, "ros_discovery_mode": "multicast",
            "ros_automatic_discovery_range": discovery_range, "ros_static_peers": list(static_peers)}
    return {name: value for name, value in host_environment(typed(data), distro, shell=True).items()
            if name != "RMW_IMPLEMENTATION"}


def render_ros_environment(distro, domain_id, discovery_range="SUBNET", static_peers=(), **more) -> str:
    return render_block(distro, ros_variables(distro, domain_id, discovery_range, static_peers), **more)


def test_jazzy_block_sources_ros_and_the_workspace_and_sets_discovery():
    text = render_ros_environment("jazzy", 11, "SUBNET", ["10.11.0.2", "team1-robot"])
    assert text.startswith("# managed by roslab")
    assert "source /opt/ros/jazzy/setup.bash" in text
    # "$HOME" quoted on its own, the rest of the path a separate single-quotable word.
    assert 'source "$HOME"/ros2_ws/install/setup.bash' in text
    assert "export ROS_DOMAIN_ID=11\n" in text
    assert "export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET\n" in text
    assert "export ROS_STATIC_PEERS='10.11.0.2;team1-robot'\n" in text


def test_humble_block_has_no_jazzy_only_variables():
    text = render_ros_environment("humble", 12, "SUBNET", ["10.11.0.2"])
    assert "source /opt/ros/humble/setup.bash" in text
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in text and "ROS_STATIC_PEERS" not in text
    assert "ROS_LOCALHOST_ONLY" not in text
    assert "export ROS_LOCALHOST_ONLY=1" in render_ros_environment("humble", 12, "LOCALHOST")


def test_the_rosdistro_index_is_exported_only_when_set():
    assert "ROSDISTRO_INDEX_URL" not in render_ros_environment("jazzy", 1)
    text = render_ros_environment("jazzy", 1, rosdistro_index_url="http://10.11.0.1/index-v4.yaml")
    assert "export ROSDISTRO_INDEX_URL=http://10.11.0.1/index-v4.yaml" in text


def run_block(block: str, home, command: str) -> subprocess.CompletedProcess:
    """Run the block in bash as a student's login would, with HOME=home, then `command`."""
    return subprocess.run(
        ["bash", "-c", block + "\n" + command], capture_output=True, text=True, check=True,
        env={"HOME": str(home), "PATH": "/usr/bin:/bin"}, cwd=home,
    )


def test_the_block_runs_in_bash_and_exports_what_it_says(tmp_path):
    block = render_ros_environment("jazzy", 30, "LOCALHOST", ["a", "b"])
    shown = run_block(block, tmp_path, "echo $ROS_DOMAIN_ID $ROS_AUTOMATIC_DISCOVERY_RANGE $ROS_STATIC_PEERS")
    assert shown.stdout == "30 LOCALHOST a;b\n"


def test_the_block_sources_the_workspace_under_the_users_home(tmp_path):
    # A legal workspace_dir with every character the schema allows besides letters.
    workspace_dir = "~/ros2_ws.v+1/my-lab_2"
    assert settings.check_value(settings.SETTINGS["workspace_dir"], workspace_dir) is None
    setup = tmp_path / "ros2_ws.v+1" / "my-lab_2" / "install" / "setup.bash"
    setup.parent.mkdir(parents=True)
    setup.write_text("echo sourced the workspace\n")
    block = render_ros_environment("jazzy", 1, workspace_dir=workspace_dir)
    assert run_block(block, tmp_path, "true").stdout == "sourced the workspace\n"


SUBSHELL = "~/$(touch pwned)"


def test_a_workspace_dir_that_would_run_a_command_is_refused_by_the_schema():
    problem = settings.check_value(settings.SETTINGS["workspace_dir"], SUBSHELL)
    assert problem and "not a plain directory name" in problem


@pytest.mark.parametrize("workspace_dir", [SUBSHELL, "~/`touch pwned`", "~/x\"; touch pwned; \"", "~/it's $HOME"])
def test_even_a_value_past_the_schema_is_only_text_in_the_shell(tmp_path, workspace_dir):
    """Defence in depth (a `pyinfra --data` override skips the roster's checks)."""
    block = render_ros_environment("jazzy", 1, workspace_dir=workspace_dir)
    run_block(block, tmp_path, "true")
    assert not (tmp_path / "pwned").exists()
    # The path bash looks at is exactly the home plus the value's text.
    (word,) = [line.removeprefix("if [ -f ").removesuffix(" ]; then")
               for line in block.splitlines() if line.startswith("if [ -f ") and "install" in line]
    shown = run_block("", tmp_path, f"printf '%s\\n' {word}")
    assert shown.stdout == f"{tmp_path}/{workspace_dir[2:]}/install/setup.bash\n"


def test_a_value_with_a_newline_is_refused_not_written():
    with pytest.raises(ValueError, match="single line"):
        render_ros_environment("jazzy", 1, static_peers=["10.0.0.1\nexport ROS_DOMAIN_ID=0"])


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_the_block_exports_exactly_the_ros_variables(tmp_path, distro):
    block = render_ros_environment(distro, 42, "OFF", ["10.0.0.2", "team1-robot"])
    env = run_block(block, tmp_path, "env").stdout.splitlines()
    exported = dict(line.split("=", 1) for line in env if line.startswith("ROS_"))
    assert exported == ros_variables(distro, 42, "OFF", ["10.0.0.2", "team1-robot"])


# The deploy on a fake host
# -------------------------


def data(**more) -> dict:
    return {**settings.defaults(), "ssh_user": "student", "roslab_team": "team1",
            "roslab_role": "main", "ros_domain_id": 11, **more}


def test_the_deploy_writes_the_block_into_the_login_users_bashrc():
    host = FakeUbuntu("noble")
    result = plan(shell_env, host.facts(), data())
    assert not result.failed
    (bashrc,) = [text for path, text in result.uploads().items() if path == "/home/student/.bashrc"]
    assert "export ROS_DOMAIN_ID=11" in bashrc and 'source "$HOME"/ros2_ws/install/setup.bash' in bashrc


def test_a_login_user_missing_on_the_host_stops_that_host_only():
    result = plan(shell_env, FakeUbuntu("noble").facts(), data(login_user="nobody2"))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi (team team1)" in error and "login_user 'nobody2' does not exist" in error
