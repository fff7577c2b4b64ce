"""BootFinished (roslab/ops/systemd.py): a run right after a reboot waits for systemd to finish
starting the host. Its command runs here, on this machine's sh, against a stand-in `systemctl`
(a script that answers `is-system-running` as a booting host would)."""

from __future__ import annotations

import subprocess

from roslab.ops.systemd import BootFinished

STANDIN = """#!/bin/sh
# stand-in for systemctl is-system-running [--wait]: "starting" until --wait, which takes $SECONDS_LEFT s
case "$*" in
  "is-system-running --wait") sleep "$SECONDS_LEFT"; echo "$AFTER";;
  "is-system-running") echo "$NOW";;
esac
"""


def read(tmp_path, now: str, after: str = "running", seconds_left: float = 0, timeout: int = 30):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "systemctl").write_text(STANDIN)
    (bin_dir / "systemctl").chmod(0o755)
    fact = BootFinished()
    done = subprocess.run(["sh", "-c", fact.command(timeout=timeout)], capture_output=True, text=True, timeout=30,
                          env={"PATH": f"{bin_dir}:/usr/bin:/bin", "NOW": now, "AFTER": after,
                               "SECONDS_LEFT": str(seconds_left)})
    return fact.process(done.stdout.splitlines())


def test_a_booted_host_is_read_without_waiting(tmp_path):
    assert read(tmp_path, "running") == {"waited": False, "seconds": 0, "state": "running", "timed_out": False}
    assert read(tmp_path, "degraded")["waited"] is False


def test_a_booting_host_is_waited_for_and_the_wait_is_said(tmp_path):
    boot = read(tmp_path, "starting", after="degraded", seconds_left=1.2)
    assert boot["waited"] and boot["state"] == "degraded" and not boot["timed_out"]
    assert 1 <= boot["seconds"] <= 3, boot


def test_a_host_still_booting_at_the_timeout_is_named_as_such(tmp_path):
    boot = read(tmp_path, "starting", seconds_left=5, timeout=1)
    assert boot["waited"] and boot["timed_out"] and boot["state"] == ""


def test_a_host_without_systemd_has_no_boot_to_wait_for(tmp_path):
    fact = BootFinished()
    done = subprocess.run(["/bin/sh", "-c", fact.command(timeout=5)], capture_output=True, text=True, timeout=10,
                          env={"PATH": str(tmp_path)})  # no systemctl on the PATH (sh found by its path)
    assert fact.process(done.stdout.splitlines()) is None


def test_the_first_step_is_still_the_deploy_the_summary_names():
    # a failure while the host is read (a lost connection, a wrong sudo password) is named in
    # this step: the boot wait's helper sits beside it, not under its decorator
    from deploy.common import said_boot_wait, supported_host

    assert getattr(supported_host, "deploy_name", None) == \
        "The host runs an Ubuntu release that has packages for its ROS 2 distro"
    assert getattr(said_boot_wait, "deploy_name", None) is None
