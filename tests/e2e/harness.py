"""Drive a sandbox classroom from the end-to-end tests: boot, reach hosts, run deploys.

Each test module uses its own sandbox instance (name and subnet), so modules never
share hosts and a failing module can't leave state for the next one. Every instance
that is brought up is brought down again, also when a test fails.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

from roslab.roster import load_roster

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
STATE_ROOT = Path("/run/roslab/sandbox")


def require_sandbox_support() -> None:
    """Skip (with the reason) where a sandbox cannot boot."""
    if os.geteuid() != 0:
        pytest.skip("the sandbox classroom needs root (network namespaces, systemd-nspawn)")
    if shutil.which("systemd-nspawn") is None:
        pytest.skip("systemd-nspawn is missing: run scripts/install-host-tools")


@dataclass
class DeployRun:
    """One `pyinfra ... --json` run: exit code, output, and what changed where."""

    returncode: int
    stdout: str
    stderr: str
    changed: dict[str, set[str]] = field(default_factory=dict)  # operation -> hosts it changed

    def changed_hosts(self) -> set[str]:
        return set().union(*self.changed.values()) if self.changed else set()

    def changes_on(self, host: str) -> list[str]:
        return sorted(name for name, hosts in self.changed.items() if host in hosts)

    @property
    def output(self) -> str:
        return self.stdout + self.stderr


@dataclass
class Sandbox:
    instance: str
    subnet: str
    hosts: int | None = None

    @property
    def env(self) -> dict[str, str]:
        return {**os.environ, "ROSLAB_SANDBOX": self.instance, "ROSLAB_SANDBOX_SUBNET": self.subnet}

    @property
    def state_dir(self) -> Path:
        return STATE_ROOT / self.instance

    @property
    def roster_path(self) -> Path:
        return self.state_dir / "roster.yaml"

    def roslab(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        return subprocess.run(
            [str(BIN / "roslab"), "sandbox", *args],
            cwd=REPO, env=self.env, check=check, capture_output=True, text=True,
        )

    def up(self) -> None:
        self.roslab("down", check=False)  # leftovers of an interrupted run
        args = ["up"] + (["--hosts", str(self.hosts)] if self.hosts else [])
        proc = self.roslab(*args, check=False)
        if proc.returncode != 0:
            self.roslab("down", check=False)
            raise AssertionError(f"sandbox up failed:\n{proc.stdout}\n{proc.stderr}")

    def down(self) -> None:
        self.roslab("down", check=False)

    def reset(self, *hosts: str) -> None:
        for host in hosts:
            self.roslab("reset", host)

    def roster(self):
        return load_roster(self.roster_path)

    def roster_data(self) -> dict:
        return yaml.safe_load(self.roster_path.read_text())

    def host_names(self) -> list[str]:
        return [h.name for team in self.roster().teams for h in team.hosts]

    def ssh(self, host: str, command: str, check: bool = True) -> subprocess.CompletedProcess:
        """Run a plain shell command on a host as its login user, over real SSH."""
        classroom = self.roster()
        target = next(h for team in classroom.teams for h in team.hosts if h.name == host)
        data = dict(target.data)
        proc = subprocess.run(
            [
                "ssh", "-i", str(data["ssh_key"]),
                "-o", "BatchMode=yes", "-o", "StrictHostKeyChecking=no",
                "-o", "UserKnownHostsFile=/dev/null", "-o", "LogLevel=ERROR",
                "-o", "ConnectTimeout=10",
                f"{data.get('ssh_user', 'ubuntu')}@{target.address}",
                command,
            ],
            capture_output=True, text=True, timeout=300,
        )
        if check and proc.returncode != 0:
            raise AssertionError(
                f"on {host}: {command!r} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
            )
        return proc

    def sudo(self, host: str, command: str, check: bool = True) -> subprocess.CompletedProcess:
        return self.ssh(host, "sudo -n sh -c " + shlex.quote(command), check=check)

    def deploy(
        self,
        *args: str,
        roster: Path | None = None,
        deploy_file: str = "deploy.py",
        timeout: int = 1800,
    ) -> DeployRun:
        """Run pyinfra on this sandbox (or on `roster`, a changed copy of its roster)."""
        env = self.env
        if roster is None:
            inventory = "inventories/sandbox.py"
        else:
            inventory = "inventories/lab.py"
            env = {**env, "ROSLAB_ROSTER": str(roster)}
        proc = subprocess.run(
            [str(BIN / "pyinfra"), "-y", "--json", *args, inventory, deploy_file],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout,
        )
        run = DeployRun(proc.returncode, proc.stdout, proc.stderr)
        try:
            document = json.loads(proc.stdout)
        except json.JSONDecodeError:
            return run
        if document.get("results"):
            for op in document["results"]["operations"]:
                if op["success"]:
                    run.changed.setdefault(op["name"], set()).update(op["success"])
        else:  # a dry run: the plan says which hosts each operation would change
            for op in document.get("plan", []):
                if op["hosts_with_change"]:
                    run.changed.setdefault(op["name"], set()).update(op["hosts_with_change"])
        return run

    def changed_roster(self, tmp_path: Path, edit) -> Path:
        """A copy of the sandbox roster, changed by `edit(data)`, as a real user would edit theirs."""
        data = self.roster_data()
        edit(data)
        path = tmp_path / "roster.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path


@pytest.fixture(scope="module")
def module_sandbox(request):
    """The sandbox named by the module's SANDBOX_INSTANCE/SANDBOX_SUBNET, up for the module."""
    require_sandbox_support()
    sandbox = Sandbox(
        request.module.SANDBOX_INSTANCE,
        request.module.SANDBOX_SUBNET,
        getattr(request.module, "SANDBOX_HOSTS", None),
    )
    sandbox.up()
    try:
        yield sandbox
    finally:
        sandbox.down()
