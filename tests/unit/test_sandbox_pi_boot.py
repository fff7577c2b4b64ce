"""The sandbox's Pi boot partition (roslab/sandbox/pi_boot.py): which hosts get it, and that it is
Ubuntu's files where roslab's deploys look for a Pi's boot partition."""

from __future__ import annotations

from ipaddress import IPv4Network

import pytest

from roslab import boards
from roslab.ops import boot_config
from roslab.sandbox import lifecycle, pi_boot, upstream
from roslab.sandbox.instance import Instance
from roslab.settings import SETTINGS


@pytest.mark.parametrize("release", sorted(pi_boot.CONFIG_TXT))
@pytest.mark.parametrize("board", boards.PI_NAMES)
def test_a_pi_gets_ubuntus_config_and_cmdline_where_the_deploys_look(board, release):
    files = pi_boot.boot_files(board, release)
    # the same paths the boot config deploy detects a Pi's boot partition by
    assert {boot_config.CONFIG_TXT, boot_config.CMDLINE_TXT} <= set(files)
    config, _ = files[boot_config.CONFIG_TXT]
    first, rest = config.split("\n", 1)
    assert first.startswith("# roslab sandbox STAND-IN") and "pi-gadget" in first
    assert rest == pi_boot.CONFIG_TXT[release]
    assert rest.startswith("[all]\n") and "kernel=vmlinuz\n" in rest and "[pi4]\n" in rest
    cmdline, _ = files[boot_config.CMDLINE_TXT]
    assert cmdline.count("\n") == 1 and cmdline.endswith("\n")  # one line, no comment
    assert "console=serial0,115200" in cmdline.split() and "root=LABEL=writable" in cmdline.split()
    assert "STAND-IN" in files[f"{pi_boot.BOOT_PARTITION}/README.roslab-sandbox"][0]


def test_the_releases_differ_as_ubuntus_images_do():
    assert "multipath=off" in pi_boot.CMDLINE_TXT["24.04"] and "multipath=off" not in pi_boot.CMDLINE_TXT["22.04"]
    assert "quiet splash" in pi_boot.CMDLINE_TXT["22.04"]
    assert "disable_fw_kms_setup=1" in pi_boot.CONFIG_TXT["24.04"] and "[pi3+]" in pi_boot.CONFIG_TXT["24.04"]


@pytest.mark.parametrize("board, release", [("pc", "24.04"), (None, "24.04"), ("pi4", "26.04")])
def test_no_boot_partition_for_a_pc_an_unsaid_board_or_a_release_without_ubuntus_files(board, release):
    assert pi_boot.boot_files(board, release) == {}


def test_the_pi_boards_are_the_board_records_that_are_a_pi_and_the_setting_takes_every_record():
    check = SETTINGS["board"].check
    assert all(check(board.name) is None for board in boards.BOARDS)
    assert check("pi6") is not None
    assert pi_boot.PI_BOARDS == tuple(board.name for board in boards.BOARDS if board.raspberry_pi)


def test_sandbox_robots_are_pi4s_and_mains_pcs_in_the_plan_and_the_written_roster():
    instance = Instance("rl-pi", IPv4Network("10.213.205.0/24"))
    planned = instance.plan_hosts(4)
    assert {host.name: host.board for host in planned} == {
        "team1-main": "pc", "team1-robot": "pi4", "team2-main": "pc", "team2-robot": "pi4"}
    written = lifecycle.roster(lifecycle.Classroom(instance, planned),
                               upstream.Upstream(url="http://10.213.205.1:8080", ros_apt_source_sha256={}))
    boards = {name: data["board"] for team in written["teams"].values() for name, data in team["hosts"].items()}
    assert boards == {"team1-main": "pc", "team1-robot": "pi4", "team2-main": "pc", "team2-robot": "pi4"}


def test_a_class_rosters_board_is_kept_and_an_unsaid_one_follows_the_role():
    instance = Instance("rl-pi", IPv4Network("10.213.205.0/24"))
    members = [{"name": "a-main", "team": "a", "role": "main", "release": "24.04", "board": "pi5"},
               {"name": "a-robot", "team": "a", "role": "robot", "release": "22.04", "board": None},
               {"name": "b-robot", "team": "b", "role": "robot", "release": "22.04"}]  # an older sandbox.json
    assert [host.board for host in instance.plan_members(members)] == ["pi5", "pi4", "pi4"]
