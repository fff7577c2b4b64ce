"""`roslab init DIR`: a classroom folder a teacher runs a class from, and what roslab ships
(roslab.packaged). The wheel itself, installed outside the checkout, is converged end to end
in tests/e2e/test_run_end_e2e.py."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

from roslab import packaged
from roslab.cli import init
from roslab.cli.main import main
from roslab.roster import inventory_groups, load_roster

REPO = Path(__file__).resolve().parents[2]


def test_init_writes_a_roster_that_checks_a_private_secrets_file_and_the_pyinfra_entry_files(tmp_path, capsys,
                                                                                             monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    folder = tmp_path / "Robotics Lab"
    old_umask = os.umask(0)  # a careless umask: the secrets file is 0600 all the same
    try:
        assert main(["init", str(folder)]) == 0
    finally:
        os.umask(old_umask)
    assert "pyinfra -y inventory.py deploy.py" in capsys.readouterr().out
    modes = {path.name: stat.S_IMODE(path.stat().st_mode) for path in folder.iterdir()}
    assert modes == {"classroom.yaml": 0o644, "secrets.yaml": 0o600, "inventory.py": 0o644,
                     "deploy.py": 0o644, ".gitignore": 0o644}
    classroom = load_roster(folder / "classroom.yaml")
    assert classroom.name == "Robotics-Lab"
    assert [host.name for host in classroom.hosts] == ["team1-main", "team1-robot"]
    assert "secrets.yaml" in (folder / ".gitignore").read_text().split()
    # No key in ~/.ssh: the roster says how to add one instead of naming a missing file.
    assert "# teacher_ssh_keys:" in (folder / "classroom.yaml").read_text()


def test_the_teachers_public_key_is_named_when_there_is_one(tmp_path, monkeypatch):
    home = tmp_path / "home"
    (home / ".ssh").mkdir(parents=True)
    key = home / ".ssh" / "id_ed25519.pub"
    key.write_text("ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIHk0c0y2WmS1C0r0dPnhkqXcS3R0o1ZCnX0GZ0dUw3Jb teacher\n")
    monkeypatch.setenv("HOME", str(home))
    assert main(["init", str(tmp_path / "class")]) == 0
    classroom = load_roster(tmp_path / "class" / "classroom.yaml")
    assert all(host.data["teacher_ssh_keys"] for host in classroom.hosts)


def test_init_never_overwrites_and_writes_nothing_then(tmp_path, capsys):
    folder = tmp_path / "class"
    folder.mkdir()
    (folder / "classroom.yaml").write_text("mine\n")
    assert main(["init", str(folder)]) == 1
    assert "already has classroom.yaml; nothing was written" in capsys.readouterr().err
    assert [path.name for path in folder.iterdir()] == ["classroom.yaml"]
    assert (folder / "classroom.yaml").read_text() == "mine\n"


def test_the_folders_inventory_gives_pyinfra_the_rosters_groups(tmp_path):
    assert main(["init", str(tmp_path / "class")]) == 0
    inventory = tmp_path / "class" / "inventory.py"
    script = ("import runpy, sys; g = runpy.run_path(sys.argv[1]); "
              "print(sorted(k for k in g if not k.startswith('_')))")
    env = {key: value for key, value in os.environ.items() if key != "ROSLAB_ROSTER"}
    done = subprocess.run([sys.executable, "-c", script, str(inventory)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    expected = sorted(inventory_groups(load_roster(tmp_path / "class" / "classroom.yaml")))
    assert done.stdout.strip() == str(expected)


def test_the_shipped_deploy_and_nodes_are_the_checkouts_in_a_checkout():
    assert packaged.deploy_file() == REPO / "deploy.py"
    assert packaged.nodes_dir() == REPO / "nodes"
    assert (packaged.nodes_dir() / "roslab_demo" / "package.xml").is_file()
    assert init.DEPLOY.count("\n") < 8 and "run_deploy" in init.DEPLOY
