"""roslab status's reading of a launch service's journal: one line per node that died, and why."""

from __future__ import annotations

from pathlib import Path

from roslab.cli import launch_journal

JOURNAL = Path(__file__).parent / "fixtures/journals/osr_launch_journal.txt"


def test_the_rovers_journal_names_each_dead_node_with_its_own_reason():
    lines = JOURNAL.read_text().splitlines()
    assert launch_journal.summary("osr_startup", lines) == [
        "osr_startup: roboclaw_wrapper died once in the last minute: Exception: Unable to connect to serial port /dev/serial1.",
        "osr_startup: rover died 2 times in the last minute: ModuleNotFoundError: No module named 'tf2_ros'",
        "osr_startup: servo_control died 2 times in the last minute: ImportError: cannot import name 'ServoKit' from "
        "'adafruit_servokit' (/home/ubuntu/osr_venv/lib/python3.11/site-packages/adafruit_servokit.py)",
    ]


def test_a_fatal_log_line_or_the_exit_code_says_why_and_running_nodes_are_not_listed():
    lines = [
        "[INFO] [launch]: All log files can be found below /home/ubuntu/.ros/log/x",
        "[INFO] [joy_node-5]: process started with pid [11]",
        "[INFO] [driver-1]: process started with pid [12]",
        "[driver-1] \x1b[31m[FATAL] [1795718486.319942666] [driver]: no lidar on /dev/ttyUSB0\x1b[0m",
        "[ERROR] [driver-1]: process has died [pid 12, exit code 1, cmd '/opt/x/driver'].",
        "[INFO] [quiet-2]: process started with pid [13]",
        "[ERROR] [quiet-2]: process has died [pid 13, exit code -11, cmd '/opt/x/quiet'].",
        "[joy_node-5] roslab sandbox stand-in: joy joy_node (the shared runtime has no joy); staying up",
    ]
    assert launch_journal.died_nodes(lines) == {"driver": (1, "no lidar on /dev/ttyUSB0"),
                                                "quiet": (1, "exit code -11")}
    assert launch_journal.summary("robot", lines[:3]) == []


def test_the_read_is_the_last_minute_bounded_and_names_the_unit():
    assert launch_journal.command("osr_startup") == (
        "journalctl -u osr_startup --since=-60s --no-pager -o cat 2>/dev/null"
        " | grep -E 'process has died|Error|Exception|FATAL|ERROR' | tail -n 2000")


def test_the_kept_lines_are_all_a_summary_needs(tmp_path):
    # The host's grep keeps every line died_nodes reads: the same summary from the whole journal.
    import re
    import subprocess

    lines = JOURNAL.read_text().splitlines()
    kept = subprocess.run(["grep", "-E", launch_journal._KEPT], input="\n".join(lines) + "\n",
                          capture_output=True, text=True).stdout.splitlines()
    assert len(kept) < len(lines)
    assert launch_journal.summary("osr_startup", kept) == launch_journal.summary("osr_startup", lines)
    assert all(re.search(launch_journal._KEPT, line) for line in kept)
