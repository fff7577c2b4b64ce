"""A long colcon build says which package it is at (roslab/ros/colcon_progress.py): the build
script's lines run here in bash against a stand-in `colcon` (a script printing colcon's own
console lines), and the lines reach the run's "still running" words."""

from __future__ import annotations

import subprocess

from roslab.ros.colcon_progress import PREFIX, Builds, build_lines, tapped

STANDIN = """#!/bin/sh
# stand-in for colcon: `list` names 3 packages, `build` prints colcon's start/end lines
case "$1" in
  list) printf 'a\\nb\\nc\\n';;
  build) echo "Starting >>> microxrcedds_agent"; echo "some compiler line"
         echo "Finished <<< microxrcedds_agent [12.3s]"; echo "Starting >>> micro_ros_agent"
         echo "Failed   <<< micro_ros_agent [1.0s, exited with code 2]"; exit "${COLCON_EXIT:-0}";;
esac
"""


def build(tmp_path, exit_status: int) -> tuple[subprocess.CompletedProcess, str]:
    (tmp_path / "bin").mkdir(exist_ok=True)
    (tmp_path / "bin" / "colcon").write_text(STANDIN)
    (tmp_path / "bin" / "colcon").chmod(0o755)
    count, condition = build_lines("colcon build --executor sequential", "build.log", "--base-paths src")
    script = f"cd {tmp_path}\n{count}\nif {condition}; then echo built; else status=$?; echo \"failed $status\"; fi"
    done = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=30,
                          env={"PATH": f"{tmp_path / 'bin'}:/usr/bin:/bin", "COLCON_EXIT": str(exit_status)})
    return done, (tmp_path / "build.log").read_text()


def test_the_build_prints_a_line_per_package_event_and_keeps_colcons_output_in_its_log(tmp_path):
    done, log = build(tmp_path, 0)
    assert done.stdout.splitlines() == [f"{PREFIX}packages 3", f"{PREFIX}building microxrcedds_agent",
                                        f"{PREFIX}built microxrcedds_agent", f"{PREFIX}building micro_ros_agent",
                                        f"{PREFIX}failed micro_ros_agent", "built"]
    assert "some compiler line" in log and "Finished <<< microxrcedds_agent [12.3s]" in log


def test_a_failed_build_keeps_colcons_exit_status(tmp_path):
    done, _ = build(tmp_path, 2)
    assert done.stdout.splitlines()[-1] == "failed 2"


def test_the_words_say_the_package_and_how_many_of_how_many_are_built():
    builds = Builds()
    assert builds.words("team2-robot") is None
    lines = [f"{PREFIX}packages 5", f"{PREFIX}building microxrcedds_agent", f"{PREFIX}built microxrcedds_agent",
             f"{PREFIX}building micro_ros_agent", "a line that is not progress"]
    stream = [line + "\n" for line in lines]
    tapping = Builds()
    import roslab.ros.colcon_progress as progress

    kept, progress.BUILDS = progress.BUILDS, tapping
    try:  # pyinfra's reader gets every line back, the progress lines also told to BUILDS
        assert list(tapped(iter(stream), "\x1b[1m[team2-robot]\x1b[0m ")) == stream
    finally:
        progress.BUILDS = kept
    assert tapping.words("team2-robot") == "building micro_ros_agent (1 of 5 built)"
    assert tapping.words("team1-robot") is None
    tapping.clear()
    assert tapping.words("team2-robot") is None
