"""How a run ends, on sandbox hosts, with the faults injected for real: the summary's lines,
its exit code (the process's), and `roslab status` after it.

One converge of the freshly imaged class, then, in order:
- `--dry` on the converged class: every host `ok`, exit 0 (no "changed" for a reload that
  only follows a change);
- no -y and standard input closed (cron, CI): one line, no traceback, exit 1, nothing run;
- every host refused (nothing listens on the roster's SSH port): the summary still comes,
  every host failed in "connect", exit 1;
- a wrong sudo password (team1-main made to ask for one, the roster's secret wrong): the
  host's line names `sudo_password_secret`, the other host of the team carries on;
- SIGINT to pyinfra while it executes (team2-robot freshly imaged): exit 130, each host
  `interrupted` in the step it had not finished, recorded; `roslab status` exits 1;
- apt-get killed on the host during ROS 2's install: the host's line gives the signal and
  exit status, the others carry on, exit 1;
- an installed roslab (the wheel in a fresh venv, a `roslab init` folder) heals the host
  (dpkg's interrupted install finished), exit 0, and
  `roslab status` exits 0 again.
"""

from __future__ import annotations

import shlex
import signal
import subprocess
import sys
import time

import pytest
import yaml

from roslab.reporting import runs
from tests.e2e.conftest import BIN, REPO, summary_lines

pytestmark = pytest.mark.e2e

HOSTS = ("team1-main", "team1-robot", "team2-main", "team2-robot")
FRESH = "team2-robot"  # re-imaged mid-module: its ROS 2 install is the long step to stop
SUDO_HOST = "team1-main"
PASSWORD_RULE = "/etc/sudoers.d/99-roslab-e2e-sudo-password"
INSTALL_STEP = "ROS 2 is installed for the host's distro and role | Ensure ROS 2 humble is installed"


def summary_block(stderr: str) -> tuple[str, dict[str, str], str]:
    """(header, host -> row, last line) of the last `--> roslab summary` block, squeezed."""
    header, *rows, last = summary_lines(stderr)
    return header, {row.split()[0]: row for row in rows}, last


def pyinfra(sandbox, *args: str, inventory: str = "inventories/sandbox.py", env: dict | None = None,
            stdin=subprocess.DEVNULL, timeout: float = 900) -> subprocess.CompletedProcess:
    """`pyinfra ARGS INVENTORY deploy.py` as a teacher (or cron) runs it: no --json."""
    return subprocess.run([str(BIN / "pyinfra"), *args, inventory, "deploy.py"], cwd=REPO,
                          env={**sandbox.env, **(env or {})}, stdin=stdin, capture_output=True,
                          text=True, timeout=timeout)


def status(sandbox) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "roslab", "status", str(sandbox.roster_path)],
                          env=sandbox.env, capture_output=True, text=True, timeout=120)


def roster_copy(sandbox, tmp_path, **classroom) -> str:
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["classroom"].update(classroom)
    path = tmp_path / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


def started_run(sandbox, log_path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([str(BIN / "pyinfra"), "-y", *args, "inventories/sandbox.py", "deploy.py"],
                            cwd=REPO, env=sandbox.env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=open(log_path, "w"), text=True)


def wait_for(predicate, what: str, timeout: float = 300, every: float = 0.5):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="module")
def converged(default_class):
    """The session's converged default class, restored for this module (fresh hosts after it)."""
    assert sorted(host.name for host in default_class.hosts) == sorted(HOSTS)
    return default_class


def test_dry_on_a_converged_class_is_ok_for_every_host(converged):
    run = pyinfra(converged, "--dry")

    assert run.returncode == 0, run.stderr[-4000:]
    header, rows, last = summary_block(run.stderr)
    assert header == "--> roslab summary (nothing was executed: changed = would change)"
    assert rows == {name: f"{name} ok" for name in HOSTS}, rows
    assert last == "exit code 0: 0 failed, 0 changed, 4 ok (4 hosts)"


def test_without_a_terminal_and_without_y_the_run_ends_in_one_line_not_a_traceback(converged):
    before = runs.runs_path(converged.roster_path).read_bytes()

    run = pyinfra(converged)  # no -y; standard input is /dev/null, as under cron

    assert run.returncode == 1, run.stderr[-4000:]
    assert "Traceback" not in run.stderr and "EOFError" not in run.stderr, run.stderr[-4000:]
    assert ("--> roslab: pyinfra asked a question (a confirmation, or a password) but standard input is "
            "closed (cron, CI, no terminal): nothing more was executed; run with -y") in run.stderr
    _, rows, last = summary_block(run.stderr)
    assert rows == {name: f"{name} not run" for name in HOSTS}, rows
    assert last == ("exit code 1: no one could answer pyinfra (standard input is closed; use -y); "
                    "0 failed, 0 changed, 0 ok, 4 not run (4 hosts)")
    assert runs.runs_path(converged.roster_path).read_bytes() == before  # nothing ran: nothing recorded


def test_when_every_host_is_refused_the_summary_still_names_each(converged, tmp_path):
    roster = roster_copy(converged, tmp_path, ssh_port=2)  # nothing listens there

    run = pyinfra(converged, "-y", inventory="inventories/lab.py", env={"ROSLAB_ROSTER": roster})

    assert run.returncode == 1, run.stderr[-4000:]
    _, rows, last = summary_block(run.stderr)
    for name in HOSTS:
        address = converged.host(name).address
        assert rows[name] == (f'{name} failed in "connect": Could not connect ([Errno None] Unable to '
                              f"connect to port 2 on {address})"), rows[name]
    assert last.startswith("exit code 1: ") and last.endswith("4 failed, 0 changed, 0 ok (4 hosts)"), last


def test_a_wrong_sudo_password_names_sudo_password_secret(converged, tmp_path):
    password = "Right-Pass-19"
    set_password = subprocess.run(
        converged_ssh(converged, SUDO_HOST, "sudo -n chpasswd"), input=f"ubuntu:{password}\n",
        capture_output=True, text=True, timeout=60)
    assert set_password.returncode == 0, set_password.stderr
    # Read last, this rule wins over the sandbox's password-less one (90-roslab-sandbox).
    rule = "ubuntu ALL=(ALL:ALL) ALL\\n"
    converged.sudo(SUDO_HOST, f"printf '{rule}' > {PASSWORD_RULE}", check=True)
    try:
        assert converged.ssh(SUDO_HOST, "sudo -n true").returncode != 0  # sudo now asks
        secrets = tmp_path / "secrets.yaml"
        secrets.write_text("lab_sudo: Wrong-Pass-19\n")
        secrets.chmod(0o600)
        roster = roster_copy(converged, tmp_path, secrets_file="secrets.yaml", sudo_password_secret="lab_sudo")

        run = pyinfra(converged, "-y", "--limit", "team1", inventory="inventories/lab.py",
                      env={"ROSLAB_ROSTER": roster})
    finally:
        restored = converged.ssh(SUDO_HOST, f"echo {shlex.quote(password)} | sudo -S -p '' rm -f {PASSWORD_RULE}")
        assert restored.returncode == 0, restored.stderr
        assert converged.ssh(SUDO_HOST, "sudo -n true").returncode == 0  # password-less again

    assert run.returncode == 1, run.stderr[-4000:]
    _, rows, last = summary_block(run.stderr)
    assert rows[SUDO_HOST].startswith(f'{SUDO_HOST} failed in "'), rows[SUDO_HOST]
    assert rows[SUDO_HOST].endswith(
        "sudo refused the password from the roster's sudo_password_secret: the secret it names does not "
        "hold this host's sudo password (sudo: 3 incorrect password attempts)"), rows[SUDO_HOST]
    assert rows["team1-robot"] == "team1-robot ok"
    assert last == "exit code 1: 1 failed, 0 changed, 1 ok (2 hosts)"
    assert "Wrong-Pass-19" not in run.stderr + run.stdout


def converged_ssh(sandbox, host: str, command: str) -> list[str]:
    from roslab.sandbox import lifecycle

    return lifecycle.ssh_argv(sandbox.instance, sandbox.host(host).address, command, host_name=host)


def test_ctrl_c_exits_130_and_names_each_unfinished_host_and_step(converged, tmp_path):
    converged.reset(FRESH)
    log = tmp_path / "pyinfra.log"
    process = started_run(converged, log)
    try:
        wait_for(lambda: "--> Beginning operation run" in log.read_text(), "the run to start executing")
        time.sleep(2)
        process.send_signal(signal.SIGINT)
        code = process.wait(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    stderr = log.read_text()

    assert code == 130, stderr[-4000:]
    _, rows, last = summary_block(stderr)
    assert rows[FRESH].startswith(f'{FRESH} interrupted in "'), rows[FRESH]
    assert rows[FRESH].endswith('": the run was stopped by SIGINT (Ctrl-C) before this step finished here')
    assert all(row.split()[1] != "changed" for row in rows.values()), rows
    assert last.startswith("exit code 130: stopped by SIGINT (Ctrl-C); "), last
    assert runs.read_runs(converged.roster_path)[FRESH].result == "interrupted"

    after = status(converged)
    assert after.returncode == 1, after.stdout + after.stderr
    assert "failed in their last run: " in after.stderr and FRESH in after.stderr


def test_a_killed_install_shows_the_signal_and_the_next_run_heals_it(converged, tmp_path):
    log = tmp_path / "pyinfra.log"
    process = started_run(converged, log)
    try:
        wait_for(lambda: converged.ssh(FRESH, "pgrep -f '^apt-get .* install -- ros-humble'").returncode == 0,
                 "apt-get to install ROS 2 on the host")
        time.sleep(3)  # into the download or the unpacking
        killed = converged.sudo(FRESH, "pkill -KILL -f '^apt-get .* install -- ros-humble'")
        assert killed.returncode == 0, killed
        code = process.wait(timeout=600)
    finally:
        if process.poll() is None:
            process.kill()
    stderr = log.read_text()

    assert code == 1, stderr[-4000:]
    _, rows, last = summary_block(stderr)
    # The class's middleware comes after the dev tools, unless it is Fast DDS (in ros-base): on a
    # real runtime the sandbox's roster names Cyclone DDS (roslab/sandbox/upstream.py).
    middleware = yaml.safe_load(converged.roster_path.read_text())["classroom"].get("ros_middleware")
    # The step's title names two packages and counts the rest (deploy/ros_install.py).
    packages = "ros-humble-ros-base, ros-dev-tools" + (
        " and 1 more" if middleware not in (None, "rmw_fastrtps_cpp") else "")
    assert rows[FRESH] == (f'{FRESH} failed in "{INSTALL_STEP} ({packages})": '
                           "roslab: apt-get install was killed by signal SIGKILL (exit status 137)"), rows[FRESH]
    for name in set(HOSTS) - {FRESH}:
        assert rows[name] == f"{name} ok", rows[name]
    assert last == "exit code 1: 1 failed, 0 changed, 3 ok (4 hosts)"



def test_an_installed_roslab_run_from_an_init_folder_heals_the_class(converged, tmp_path):
    """The wheel, installed into a fresh venv outside the checkout; `roslab init` makes the
    folder; the class (with the host whose install was killed) converges from there, with
    the deploy and the demo nodes of the installed package."""
    wheels = tmp_path / "wheels"
    built = subprocess.run([str(BIN / "pip"), "wheel", "--no-deps", "-q", "-w", str(wheels), str(REPO)],
                           capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stderr[-3000:]
    assert "project.license" not in built.stderr  # no setuptools warnings about it
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    clean_env = {key: value for key, value in converged.env.items() if key not in ("PYTHONPATH", "ROSLAB_ROSTER")}
    installed = subprocess.run([str(venv / "bin/pip"), "install", "-q", *map(str, wheels.glob("*.whl"))],
                               cwd=tmp_path, env=clean_env, capture_output=True, text=True, timeout=900)
    assert installed.returncode == 0, installed.stderr[-3000:]

    folder = tmp_path / "class"
    init = subprocess.run([str(venv / "bin/roslab"), "init", str(folder)], cwd=tmp_path, env=clean_env,
                          capture_output=True, text=True, timeout=60)
    assert init.returncode == 0, init.stderr
    assert sorted(path.name for path in folder.iterdir()) == [
        ".gitignore", "classroom.yaml", "deploy.py", "inventory.py", "secrets.yaml"]
    assert (folder / "secrets.yaml").stat().st_mode & 0o777 == 0o600
    # The teacher fills in the roster: here, the sandbox class's.
    (folder / "classroom.yaml").write_text(converged.roster_path.read_text())

    run = subprocess.run([str(venv / "bin/pyinfra"), "-y", "inventory.py", "deploy.py"], cwd=folder,
                         env=clean_env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=900)

    assert run.returncode == 0, run.stderr[-6000:]
    # Compact: only the steps that changed something, and the summary is the last screen.
    assert "No changes" not in run.stderr
    assert "steps changed nothing on any host and are not shown above (-v shows every step)" in run.stderr
    assert run.stderr.rstrip().splitlines()[-1].strip().startswith("exit code 0: ")
    assert str(REPO) not in run.stderr  # nothing of the checkout: the package's deploy and nodes
    nodes = venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages/roslab/data/nodes"
    assert f"holds the packages of {nodes}" in run.stderr
    _, rows, last = summary_block(run.stderr)
    assert rows[FRESH] == f"{FRESH} changed"
    assert last == "exit code 0: 0 failed, 1 changed, 3 ok (4 hosts)"
    listed = converged.ssh(FRESH, "ls ~/ros2_ws/src; systemctl is-active roslab-nodes")
    assert listed.stdout.split() == ["roslab_bringup", "roslab_demo", "roslab_esp32", "active"], listed
    after = subprocess.run([str(venv / "bin/roslab"), "status"], cwd=folder, env=clean_env,
                           capture_output=True, text=True, timeout=120)
    assert after.returncode == 0, after.stdout + after.stderr
