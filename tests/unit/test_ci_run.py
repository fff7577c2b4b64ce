""".ci/run: real ROS 2 in the sandbox when ../shared/ros-runtime is beside the clone, and says so.

CI runs a fresh clone with `shared/` beside it; `.ci/run` then exports
ROSLAB_SANDBOX_ROS_RUNTIME before `make test`. A stand-in `make` (first on PATH) prints what
it was given instead of running the suite.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

CI_RUN = Path(__file__).resolve().parents[2] / ".ci/run"


@pytest.fixture
def clone(tmp_path):
    repo = tmp_path / "work/clone"
    (repo / ".ci").mkdir(parents=True)
    shutil.copy2(CI_RUN, repo / ".ci/run")
    tools = tmp_path / "bin"
    tools.mkdir()
    (tools / "make").write_text('#!/bin/sh\necho "make $* runtime=${ROSLAB_SANDBOX_ROS_RUNTIME-unset} '
                               'sources=${ROSLAB_SANDBOX_SOURCES-unset}"\n')
    (tools / "make").chmod(0o755)
    return repo, tools


def ci_run(repo: Path, tools: Path, **env: str) -> subprocess.CompletedProcess:
    base = {key: value for key, value in os.environ.items()
            if key not in ("ROSLAB_SANDBOX_ROS_RUNTIME", "ROSLAB_SANDBOX_SOURCES")}
    return subprocess.run([str(repo / ".ci/run")], env={**base, "PATH": f"{tools}:{base['PATH']}", **env},
                          capture_output=True, text=True, check=True, timeout=30)


def test_the_shared_runtime_beside_the_clone_is_used_and_named(clone):
    repo, tools = clone
    runtime = repo.parent / "shared/ros-runtime"
    runtime.mkdir(parents=True)
    out = ci_run(repo, tools).stdout
    assert f"REAL ROS 2 from ROSLAB_SANDBOX_ROS_RUNTIME={runtime}" in out
    assert f"make test runtime={runtime}" in out


def test_without_the_shared_runtime_the_suite_runs_on_stand_ins_and_says_so(clone):
    repo, tools = clone
    out = ci_run(repo, tools).stdout
    assert "STAND-IN ROS 2 packages" in out
    assert "make test runtime=unset" in out


def test_a_value_set_by_the_user_wins_even_an_empty_one(clone, tmp_path):
    repo, tools = clone
    (repo.parent / "shared/ros-runtime").mkdir(parents=True)
    assert "make test runtime= " in ci_run(repo, tools, ROSLAB_SANDBOX_ROS_RUNTIME="").stdout
    mine = tmp_path / "mine"
    assert f"make test runtime={mine} " in ci_run(repo, tools, ROSLAB_SANDBOX_ROS_RUNTIME=str(mine)).stdout


def test_the_robots_real_repositories_beside_the_clone_are_used_and_named(clone):
    repo, tools = clone
    runtime, sources = repo.parent / "shared/ros-runtime", repo.parent / "shared/sources"
    runtime.mkdir(parents=True)
    sources.mkdir(parents=True)
    out = ci_run(repo, tools).stdout
    assert f"the robots' REAL repositories from ROSLAB_SANDBOX_SOURCES={sources}" in out
    assert f"make test runtime={runtime} sources={sources}" in out
    # without them (or without a real runtime to build them on): stand-ins, said so
    sources.rmdir()
    out = ci_run(repo, tools).stdout
    assert "STAND-IN robot repositories" in out and "sources=unset" in out
