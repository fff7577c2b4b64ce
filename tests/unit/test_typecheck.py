"""`make test`, and so CI's `.ci/run`, runs the type check (mypy) before any test (docs/testing.md)."""

import os
import subprocess
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_make_test_runs_mypy_before_pytest():
    outer = {key: value for key, value in os.environ.items() if key not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    shown = subprocess.run(["make", "--no-print-directory", "-n", "test"], cwd=REPO, capture_output=True,
                           text=True, timeout=60, env=outer)
    assert shown.returncode == 0, shown.stderr
    lines = shown.stdout.splitlines()
    mypy = [number for number, line in enumerate(lines) if line.strip() == ".venv/bin/mypy"]
    pytest = [number for number, line in enumerate(lines) if "/pytest " in line]
    assert mypy and pytest and mypy[0] < pytest[0], shown.stdout


def test_the_type_check_covers_roslab_and_deploy_with_untyped_bodies_checked():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]
    assert config["files"] == ["roslab", "deploy"]
    assert config["check_untyped_defs"] is True
    assert (REPO / "roslab/data/deploy.py").resolve() == (REPO / "deploy.py").resolve()
