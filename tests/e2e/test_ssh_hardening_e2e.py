"""SSH hardening end to end: key-only sshd without ever losing access, on sandbox hosts over real SSH.

Runs the two SSH steps of deploy.py (tests/e2e/ssh_hardening_deploy.py: ssh_identity, then
ssh_hardening) on the session's sandbox classroom. Each host first gets what a flashed Ubuntu
Pi has and the sandbox image lacks: a password for the login user and cloud-init's drop-in
`50-cloud-init.conf` with `PasswordAuthentication yes`; so password login works before.

- team1-main (24.04) and team2-main (22.04): after a run, password login is refused (sshd
  offers publickey only) and key login works; a second run changes nothing and the host
  is still reachable;
- team1-robot: a student's broken file in sshd_config.d makes the step fail with one clear
  line; roslab's drop-in is not written, sshd keeps serving its old configuration
  (password login still works), and the host stays reachable;
- team2-robot: with `ssh_hardening_enabled: false` in the roster nothing is changed.
"""

from __future__ import annotations

import secrets

import paramiko
import pytest
import yaml

from roslab.ssh.sshd import DROPIN

pytestmark = pytest.mark.e2e

TEST_DEPLOY = "tests/e2e/ssh_hardening_deploy.py"
HARDENED = ["team1-main", "team2-main"]
BROKEN = "team1-robot"
OPTED_OUT = "team2-robot"
STUDENT_FILE = "/etc/ssh/sshd_config.d/99-student.conf"
HARDENING_OP = "Ensure sshd allows keys only"
PASSWORD = secrets.token_urlsafe(12)  # the login user's, on the sandbox hosts only


@pytest.fixture(scope="module")
def sandbox(e2e_sandbox):
    """The session's classroom, freshly imaged for this module and again after it, each
    host with a login password and cloud-init's password-login drop-in, as on a flashed Pi."""
    e2e_sandbox.reset()
    for host in e2e_sandbox.hosts:
        e2e_sandbox.sudo(
            host.name,
            f"echo 'ubuntu:{PASSWORD}' | chpasswd && "
            "echo 'PasswordAuthentication yes' > /etc/ssh/sshd_config.d/50-cloud-init.conf && "
            "systemctl reload ssh.service",
            check=True,
        )
    yield e2e_sandbox
    e2e_sandbox.reset()


def password_login(sandbox, host: str) -> str:
    """'accepted', or how sshd refused the login user's (right) password."""
    client = paramiko.SSHClient()
    client.set_missing_host_key_policy(paramiko.AutoAddPolicy())  # in memory, a sandbox host
    try:
        client.connect(sandbox.host(host).address, username="ubuntu", password=PASSWORD,
                       look_for_keys=False, allow_agent=False, timeout=10, banner_timeout=10)
        return "accepted"
    except paramiko.BadAuthenticationType as error:
        return f"refused: sshd offers {sorted(error.allowed_types)}"
    except paramiko.AuthenticationException:
        return "refused"
    finally:
        client.close()


def key_login(sandbox, host: str) -> bool:
    return sandbox.ssh(host, "true").returncode == 0


def deploy(sandbox, hosts: list[str], **settings):
    """The test deploy on `hosts`, with `settings` added to the sandbox's roster."""
    roster = yaml.safe_load(sandbox.roster_path.read_text())
    roster["classroom"].update(settings)
    path = sandbox.roster_path.with_name("roster-ssh-hardening-e2e.yaml")  # beside it: same state dir
    path.write_text(yaml.safe_dump(roster, sort_keys=False))
    try:
        limits = [word for host in hosts for word in ("--limit", host)]
        return sandbox.pyinfra(*limits, inventory="inventories/lab.py", deploy=TEST_DEPLOY,
                               env={"ROSLAB_ROSTER": str(path)}, timeout=600)
    finally:
        path.unlink()


def test_before_hardening_password_login_works(sandbox):
    # Otherwise the tests below could not tell a refused password from a broken one.
    assert [password_login(sandbox, host) for host in HARDENED] == ["accepted", "accepted"]


def test_hardening_refuses_passwords_and_keeps_key_login(sandbox):
    run = deploy(sandbox, HARDENED)
    assert run.returncode == 0, run.stderr[-4000:]
    assert {host for name, hosts in run.changed.items() if HARDENING_OP in name for host in hosts} == set(HARDENED), \
        run.stderr[-4000:]
    for host in HARDENED:
        assert password_login(sandbox, host) == "refused: sshd offers ['publickey']", host
        assert key_login(sandbox, host), host
        assert sandbox.sudo(host, "sshd -T | grep -i '^permitrootlogin '", check=True).stdout.split() == [
            "permitrootlogin", "no"]


def test_hardening_again_changes_nothing_and_never_loses_access(sandbox):
    for _ in range(2):
        run = deploy(sandbox, HARDENED)
        assert run.returncode == 0, run.stderr[-4000:]
        assert run.changed == {}, f"a re-run changed: {run.changed}"
        assert all(key_login(sandbox, host) for host in HARDENED)


def test_a_students_broken_sshd_file_stops_the_step_and_sshd_keeps_its_config(sandbox):
    sandbox.sudo(BROKEN, f"echo 'PasswordAuthentcation no' > {STUDENT_FILE}", check=True)
    run = deploy(sandbox, [BROKEN, HARDENED[0]])  # with a bystander: the other hosts carry on
    assert run.returncode != 0 and run.failed_hosts == [BROKEN], run.stderr[-4000:]
    output = run.stdout + run.stderr
    said = "roslab: sshd -t rejects the configuration, so ssh hardening changed nothing"
    # Said once while the step runs, and once more as the host's reason in the run summary.
    assert output.count(f"[{BROKEN}] {said}") == 1, output[-4000:]
    assert [line for line in output.splitlines() if line.strip().startswith(f"{BROKEN} ") and "failed" in line
            and said in line], output[-4000:]
    assert f"{STUDENT_FILE}: line 1: Bad configuration option: PasswordAuthentcation" in output
    # Nothing changed: no drop-in, nothing left behind, sshd serves the old configuration.
    assert sandbox.sudo(BROKEN, f"ls -d {DROPIN}* /run/roslab-sshd-check.* 2>/dev/null").stdout == ""
    assert key_login(sandbox, BROKEN)
    assert password_login(sandbox, BROKEN) == "accepted"
    # Once the student's file is fixed, the next run hardens the host.
    sandbox.sudo(BROKEN, f"rm {STUDENT_FILE}", check=True)
    fixed = deploy(sandbox, [BROKEN])
    assert fixed.returncode == 0, fixed.stderr[-4000:]
    assert password_login(sandbox, BROKEN) == "refused: sshd offers ['publickey']"
    assert key_login(sandbox, BROKEN)


def test_switched_off_nothing_is_changed(sandbox):
    run = deploy(sandbox, [OPTED_OUT], ssh_hardening_enabled=False)
    assert run.returncode == 0, run.stderr[-4000:]
    assert not [name for name in run.changed if "sshd" in name.lower()], run.changed
    assert sandbox.sudo(OPTED_OUT, f"test -e {DROPIN}").returncode != 0
    assert password_login(sandbox, OPTED_OUT) == "accepted"
