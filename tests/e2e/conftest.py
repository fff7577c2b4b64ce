"""End-to-end fixtures: a sandbox classroom for the session, reached over real SSH.

`e2e_sandbox` boots the dedicated instance `roslab-e2e` once per session and
always takes it down again: at the end of the session, when a test fails, on
Ctrl-C, on SIGTERM, and (as a last resort) at interpreter exit.
`fresh_hosts` gives a test freshly imaged hosts (about a second).
`default_class` gives a module the default class converged: converged once per session from
fresh hosts (`default_class_saved`), saved, and restored per module (seconds, not minutes).
"""

from __future__ import annotations

import atexit
import ipaddress
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import pytest

from roslab.sandbox import lifecycle
from roslab.sandbox.instance import Instance, SandboxHost

REPO = Path(__file__).resolve().parents[2]

# Overridable so that two checkouts (or two developers) can run the suite side by side.
E2E_INSTANCE = os.environ.get("ROSLAB_E2E_INSTANCE", "roslab-e2e")
E2E_SUBNET = os.environ.get("ROSLAB_E2E_SUBNET", "10.213.200.0/24")
BIN = Path(sys.executable).parent


def sandbox_unsupported_reason() -> str | None:
    """Why sandbox hosts cannot boot here, or None."""
    if os.geteuid() != 0:
        return "the sandbox needs root (network namespaces, mounts, systemd-nspawn)"
    for tool in ("systemd-nspawn", "mmdebstrap", "apt-ftparchive", "ip"):
        if shutil.which(tool) is None:
            return f"{tool} is missing (install systemd-container, mmdebstrap, apt-utils, iproute2)"
    return None


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str


@dataclass
class PyinfraRun:
    """One `pyinfra --json` run: what changed on which host, and what failed."""

    returncode: int
    stdout: str
    stderr: str
    # operation name -> hosts it changed (None: a run without --json, which does not say)
    changed: dict[str, set[str]] | None = field(default_factory=dict)
    failed_hosts: list[str] = field(default_factory=list)

    def changes_per_host(self) -> Counter:
        return Counter(host for hosts in self.changed.values() for host in hosts)


def parse_pyinfra_json(stdout: str) -> tuple[dict[str, set[str]], list[str]]:
    """Changed operations (name -> hosts) and failed hosts from pyinfra 3.10's --json output.

    A real run reports results (per operation: hosts with success+change in
    `success`); a --dry run has results None and lists `hosts_with_change` in the plan.
    """
    document = json.loads(stdout)
    changed: dict[str, set[str]] = {}
    if document.get("results"):
        for op in document["results"]["operations"]:
            if op["success"]:
                changed.setdefault(op["name"], set()).update(op["success"])
        return changed, document["results"]["failed_hosts"]
    for op in document.get("plan", []):
        if op["hosts_with_change"]:
            changed.setdefault(op["name"], set()).update(op["hosts_with_change"])
    return changed, []


@dataclass
class SandboxClassroom:
    """A running sandbox instance, as the tests use it."""

    instance: Instance
    hosts: list[SandboxHost]

    @property
    def env(self) -> dict[str, str]:
        return {**os.environ, "ROSLAB_SANDBOX": self.instance.name,
                "ROSLAB_SANDBOX_SUBNET": str(self.instance.subnet)}

    @property
    def roster_path(self) -> Path:
        return self.instance.roster_path

    @property
    def ros_served(self) -> dict[str, str]:
        """distro -> "stand-in" or "real (...)": what the instance's ROS archive serves
        (ROSLAB_SANDBOX_ROS_RUNTIME when it came up; docs/sandbox.md)."""
        return lifecycle.ros_served(self.instance)

    @property
    def real_ros(self) -> bool:
        """Every distro this classroom's hosts run is real ROS 2 (else the tests that run nodes skip)."""
        from roslab.ros.distro import DEFAULT_DISTRO, UBUNTU_CODENAMES

        served = self.ros_served
        distros = {DEFAULT_DISTRO[UBUNTU_CODENAMES[host.release]] for host in self.hosts}
        return all(served.get(distro, "").startswith("real") for distro in distros)

    @property
    def real_repositories(self) -> list[str]:
        """The robots' repositories this instance's git upstream serves for real (from the bundles
        ROSLAB_SANDBOX_SOURCES names, roslab/sandbox/real_sources.py), not as stand-ins."""
        return lifecycle.real_repositories(self.instance)

    def host(self, name: str) -> SandboxHost:
        return next(host for host in self.hosts if host.name == name)

    def ssh(self, host: str, command: str, check: bool = False, timeout: float = 300) -> Result:
        """Run a shell command on a host as the login user over plain ssh."""
        argv = lifecycle.ssh_argv(self.instance, self.host(host).address, command, host_name=host)
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
        if check and proc.returncode != 0:
            raise AssertionError(f"on {host}: {command!r} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
        return Result(proc.returncode, proc.stdout, proc.stderr)

    def sudo(self, host: str, command: str, check: bool = False, timeout: float = 300) -> Result:
        return self.ssh(host, f"sudo -n sh -c {shlex.quote(command)}", check=check, timeout=timeout)

    def pyinfra(self, *args: str, inventory: str = "inventories/sandbox.py", deploy: str = "deploy.py",
                env: dict[str, str] | None = None, timeout: float = 1800, json_output: bool = True) -> PyinfraRun:
        """`pyinfra [-y] --json [args] INVENTORY DEPLOY` on this sandbox, with what changed per host.

        `json_output=False`: without --json, as a teacher runs it (roslab's compact output, with
        its "still running" lines); the failed hosts are then read from roslab's summary, and
        what changed is not known (`changed` is None)."""
        # -y applies without asking; with --dry it would also skip the change detection
        # that a dry run is for, leaving the plan's hosts_with_change empty.
        confirm = [] if "--dry" in args else ["-y"]
        proc = subprocess.run(
            [str(BIN / "pyinfra"), *confirm, *(["--json"] if json_output else []), *args, inventory, deploy],
            cwd=REPO, env={**self.env, **(env or {})}, capture_output=True, text=True, timeout=timeout,
        )
        run = PyinfraRun(proc.returncode, proc.stdout, proc.stderr)
        if not json_output:
            run.changed = None
            run.failed_hosts = [words[0] for words in map(str.split, summary_lines(proc.stderr)[1:])
                                if len(words) > 1 and words[1] == "failed"]
            return run
        try:
            run.changed, run.failed_hosts = parse_pyinfra_json(proc.stdout)
        except (json.JSONDecodeError, KeyError):
            pass  # pyinfra stopped before it could report: returncode and stderr say why
        return run

    def roslab(self, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
        """`roslab ARGS` from the checkout, on this sandbox (its instance's environment)."""
        return subprocess.run([str(BIN / "roslab"), *args], cwd=REPO, env=self.env, capture_output=True,
                              text=True, timeout=timeout)

    def reset(self, *hosts: str) -> float:
        return lifecycle.reset(list(hosts) or [host.name for host in self.hosts], self.instance)

    def reboot(self, host: str) -> float:
        return lifecycle.reboot(host, self.instance)

    def save(self, name: str) -> float:
        return lifecycle.save(name, self.instance)

    def restore(self, name: str) -> float:
        return lifecycle.restore(name, self.instance)


def bring_up(name: str, subnet: str, hosts: int | None = None,
             releases: str | None = None) -> tuple[SandboxClassroom, callable]:
    """Boot an instance and return it with its idempotent teardown (also run at exit and on SIGTERM).

    `releases`: ROSLAB_SANDBOX_RELEASES for this boot only (e.g. "24.04,22.04"), the
    environment as it was afterwards."""
    if releases is not None:
        previous = os.environ.get("ROSLAB_SANDBOX_RELEASES")
        os.environ["ROSLAB_SANDBOX_RELEASES"] = releases
        try:
            return bring_up(name, subnet, hosts)
        finally:
            if previous is None:
                os.environ.pop("ROSLAB_SANDBOX_RELEASES", None)
            else:
                os.environ["ROSLAB_SANDBOX_RELEASES"] = previous
    instance = Instance(name, ipaddress.IPv4Network(subnet))
    done = False

    def teardown() -> None:
        nonlocal done
        if not done:
            done = True
            lifecycle.down(instance)

    atexit.register(teardown)
    try:
        classroom = lifecycle.up(hosts, instance)
    except BaseException:
        teardown()
        raise
    return SandboxClassroom(classroom.instance, classroom.hosts), teardown


def summary_lines(stderr: str) -> list[str]:
    """The lines of the last `--> roslab summary` block of a run's output, whitespace squeezed."""
    lines = [" ".join(line.split()) for line in stderr.splitlines()]
    start = max(i for i, line in enumerate(lines) if line.startswith("--> roslab summary"))
    block = []
    for line in lines[start:]:
        if not line:
            break
        block.append(line)
    return block


def _interrupt(signum, frame):
    # SIGTERM (a CI timeout, `kill`) would end pytest without running finalizers:
    # turn it into the interrupt Ctrl-C gives, which pytest unwinds through them.
    raise KeyboardInterrupt(f"signal {signum}")


@pytest.fixture(scope="session")
def sandbox_support():
    """Skip the test, saying why, where sandbox hosts cannot boot."""
    reason = sandbox_unsupported_reason()
    if reason:
        pytest.skip(reason)


@pytest.fixture(scope="session")
def e2e_sandbox(sandbox_support):
    """The session's sandbox classroom (instance roslab-e2e: 2 teams, 24.04 and 22.04)."""
    previous = signal.signal(signal.SIGTERM, _interrupt)
    classroom, teardown = bring_up(E2E_INSTANCE, E2E_SUBNET)
    try:
        yield classroom
    finally:
        teardown()
        signal.signal(signal.SIGTERM, previous)


@pytest.fixture
def fresh_hosts(e2e_sandbox):
    """The session sandbox with every host freshly imaged for this test, and again after it
    (whatever the test changed, e.g. an address, does not reach the next test)."""
    e2e_sandbox.reset()
    yield e2e_sandbox
    e2e_sandbox.reset()


# The saved state `default_class_saved` makes; per session, so that a session never meets one
# of an earlier session that could not take its instance down (saved states go with `down`).
DEFAULT_CLASS = f"default-class-{os.getpid()}"


@dataclass
class SavedClass:
    """The session's converge of the default class from fresh hosts, as it was saved."""

    run: PyinfraRun  # `pyinfra inventories/sandbox.py deploy.py` on freshly imaged hosts
    started: datetime  # when that run started (UTC, whole seconds, as roslab's run records)


# One host of the default class starts as a tutorial from before 2025 left it: the old-style
# ROS apt source (`ros2.list`, an expired `ros-archive-keyring.gpg`) that breaks apt today.
LEGACY_HOST = "team2-robot"
LEGACY_LIST = "/etc/apt/sources.list.d/ros2.list"
LEGACY_KEY = "/usr/share/keyrings/ros-archive-keyring.gpg"


@pytest.fixture(scope="session")
def default_class_saved(e2e_sandbox) -> SavedClass:
    """The default class converged ONCE per session from freshly imaged hosts (the sandbox's
    roster, deploy.py, no --data; LEGACY_HOST with the old-style ROS source), every host changed
    and none failed, then saved as DEFAULT_CLASS: what each module that starts from "a converged
    default class" restores. test_classroom_e2e checks this run as a classroom's first run."""
    e2e_sandbox.reset()
    e2e_sandbox.sudo(
        LEGACY_HOST,
        f"echo 'deb [arch=amd64 signed-by={LEGACY_KEY}] http://packages.ros.org/ros2/ubuntu "
        f"jammy main' > {LEGACY_LIST} && echo 'expired key' > {LEGACY_KEY}",
        check=True,
    )
    started = datetime.now(timezone.utc).replace(microsecond=0)
    run = e2e_sandbox.pyinfra()
    assert run.returncode == 0 and not run.failed_hosts, run.stderr[-6000:]
    assert set(run.changes_per_host()) == {host.name for host in e2e_sandbox.hosts}, run.changed
    print(f"\ndefault class converged from fresh hosts, saved in {e2e_sandbox.save(DEFAULT_CLASS):.1f} s")
    return SavedClass(run, started)


@pytest.fixture(scope="module")
def default_class(e2e_sandbox, default_class_saved):
    """The session sandbox with the saved converged default class restored for this module (its
    hosts' disks and roslab's run records), and freshly imaged hosts after it for the next module.
    test_summary_e2e's no-op on it reports 0 changed: restored is converged."""
    print(f"\ndefault class restored, ssh ready after {e2e_sandbox.restore(DEFAULT_CLASS):.1f} s")
    for host in e2e_sandbox.hosts:  # booted to the end, as the converge left it: its services run
        e2e_sandbox.ssh(host.name, "systemctl is-system-running --wait", timeout=180)
    yield e2e_sandbox
    e2e_sandbox.reset()


@pytest.fixture(scope="module")
def default_class_publishing(default_class):
    """The converged default class for a module that moves its upstream (`roslab sandbox
    publish PACKAGE --bump`): the archives as `up` served them again after the module."""
    yield default_class
    reverted = default_class.roslab("sandbox", "publish", "--revert")
    assert reverted.returncode == 0, reverted.stderr
