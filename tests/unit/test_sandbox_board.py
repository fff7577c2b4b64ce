"""`roslab sandbox board TEAM`'s choice of board by the team's robot profile: an osr team gets
the stand-in RoboClaws in its robot (roslab/sandbox/rover_board.py), an esp32_microros team the
ESP32 stand-in, any other team a clear error listing the teams that have an emulated board.
The host side (SSH, systemd-run in the robot) is replaced here by recording stand-ins of
rover_board's start/stop/state; the robots e2e runs the real one."""

from __future__ import annotations

import argparse
import textwrap

import pytest
from test_profiles import _in_tmp, rosdistro_url  # noqa: F401  (fixtures)

from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import resolve_host
from roslab.sandbox import cli, rover_board
from roslab.sandbox.system import SandboxError


def class_roster(tmp_path, url):
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent(f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {url}
          rosdep_cache_dir: cache
        teams:
          rover:
            ubuntu_release: "24.04"
            robot_profile: osr
            hosts:
              rover-main: {{role: main}}
              rover-robot: {{role: robot}}
          knob:
            ubuntu_release: "24.04"
            robot_profile: esp32_microros
            esp32_usb_serial: A1B2C3
            esp32_transport: udp
            hosts:
              knob-main: {{role: main}}
              knob-robot: {{role: robot}}
          sim:
            ubuntu_release: "24.04"
            robot_profile: sim
            hosts:
              sim-main: {{role: main}}
        """))
    return path


@pytest.fixture()
def recorded(monkeypatch):
    """What rover_board was asked to do, and on which host (nothing reaches a host)."""
    calls: list[tuple[str, str]] = []
    monkeypatch.setattr(rover_board, "start", lambda instance, host: calls.append(("start", host)) or 4242)
    monkeypatch.setattr(rover_board, "stop", lambda instance, host: calls.append(("stop", host)) or True)
    monkeypatch.setattr(rover_board, "state", lambda instance, host: calls.append(("state", host)) or "answering")
    monkeypatch.setenv("ROSLAB_SANDBOX", "rl-unit-board")
    return calls


@pytest.mark.parametrize("action, called", [("start", "start"), ("stop", "stop"), ("status", "state")])
def test_an_osr_team_gets_the_stand_in_roboclaws_in_its_robot(tmp_path, rosdistro_url, recorded, capsys,
                                                              action, called):
    path = class_roster(tmp_path, rosdistro_url)
    assert cli.run_board(argparse.Namespace(team="rover", action=action, roster=path)) == 0
    assert recorded == [(called, "rover-robot")]
    out = capsys.readouterr().out
    assert out.startswith("rover: stand-in RoboClaws 128, 129, 130 on /dev/serial1 of rover-robot")


def test_a_team_without_an_emulated_board_is_an_error_naming_the_teams_with_one(tmp_path, rosdistro_url,
                                                                                recorded):
    path = class_roster(tmp_path, rosdistro_url)
    with pytest.raises(SandboxError) as error:
        cli.run_board(argparse.Namespace(team="sim", action="start", roster=path))
    assert str(error.value) == (f"{path}: team 'sim' has no board the sandbox emulates (an ESP32 of robot_profile "
                                "esp32_microros, the RoboClaws of robot_profile osr); teams with one: knob, rover")
    with pytest.raises(SandboxError, match="team 'nobody' has no board"):
        cli.run_board(argparse.Namespace(team="nobody", action="status", roster=path))
    assert recorded == []


def test_an_esp32_team_still_gets_the_esp32_board(tmp_path, rosdistro_url, recorded, monkeypatch, capsys):
    from roslab.sandbox import esp32_board

    monkeypatch.setattr(esp32_board, "state", lambda state_dir, team: f"stopped ({team})")
    path = class_roster(tmp_path, rosdistro_url)
    assert cli.run_board(argparse.Namespace(team="knob", action="status", roster=path)) == 0
    assert "knob: board esp32_board_knob" in capsys.readouterr().out
    assert recorded == []


def test_the_port_and_addresses_are_the_osr_profiles():
    """/dev/serial1 is the link the osr profile's udev rule makes (roboclaw_params.yaml's device at
    v4.1.0, checked against upstream in test_devices_upstream.py); the checklist names the addresses."""
    data, problems = resolve_host(builtin_profiles()["osr"], {}, distro="jazzy", role="robot")
    assert not problems
    assert 'KERNEL=="ttyAMA0"' in data["udev_rules"] and 'SYMLINK+="serial1"' in data["udev_rules"]
    assert rover_board.PORT == "/dev/serial1"
    assert "addresses 128, 129, 130" in " ".join(data["checklist"])
    assert rover_board.ADDRESSES == (128, 129, 130)
