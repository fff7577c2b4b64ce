"""Benchmark: first-run and no-op re-run of deploy.py on sandbox classrooms of several sizes.

For each size it boots a fresh sandbox instance, runs `pyinfra inventories/sandbox.py deploy.py`
three times (first run, then two no-op re-runs, keeping the faster re-run), and records:

- wall time of the first run and of the no-op re-run,
- remote commands per host on the no-op re-run (pyinfra's --debug log lines
  "Running command on <host>": facts and operations alike),
- how many operations the re-run changed (must be 0).

Results go to bench/results/noop_rerun.md (a table the README links) and .json.
Needs root, like the sandbox. Usage:

    .venv/bin/python bench/noop_rerun.py [--sizes 1 4 12]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
RESULTS = REPO / "bench" / "results"
INSTANCE = "roslab-bench"
SUBNET = "10.213.60.0/24"
COMMAND_LINE = re.compile(r"Running command on (\S+?):")


def sandbox(*args: str) -> None:
    subprocess.run([str(BIN / "roslab"), "sandbox", *args], check=True, env=bench_env())


def bench_env() -> dict[str, str]:
    return {**os.environ, "ROSLAB_SANDBOX": INSTANCE, "ROSLAB_SANDBOX_SUBNET": SUBNET}


def timed_deploy() -> tuple[float, Counter, str]:
    """Run deploy.py once; return wall seconds, remote commands per host, and the output."""
    started = time.monotonic()
    proc = subprocess.run(
        [str(BIN / "pyinfra"), "-y", "--json", "--debug", "inventories/sandbox.py", "deploy.py"],
        cwd=REPO, env=bench_env(), capture_output=True, text=True,
    )
    elapsed = time.monotonic() - started
    if proc.returncode != 0:
        raise SystemExit(f"deploy failed:\n{proc.stderr[-4000:]}")
    return elapsed, Counter(COMMAND_LINE.findall(proc.stderr)), proc.stdout


def measure(size: int) -> dict:
    sandbox("down")
    sandbox("up", "--hosts", str(size))
    try:
        first, _, _ = timed_deploy()
        reruns = [timed_deploy() for _ in range(2)]
        noop, commands, output = min(reruns, key=lambda r: r[0])
        per_host = sorted(commands.values())
        return {
            "hosts": size,
            "first_run_s": round(first, 2),
            "noop_rerun_s": round(noop, 2),
            "remote_commands_per_host": per_host[len(per_host) // 2] if per_host else 0,
            "remote_commands_max": max(per_host, default=0),
            "noop_changed_operations": changed_total(output),
        }
    finally:
        sandbox("down")


def changed_total(json_output: str) -> int:
    """Operations that changed something, summed over hosts (pyinfra --json: 'success' lists them)."""
    results = json.loads(json_output)["results"]
    return sum(len(op["success"]) for op in results["operations"])


def write_results(rows: list[dict]) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "noop_rerun.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = [
        "# deploy.py on sandbox classrooms: first run and no-op re-run",
        "",
        f"Measured {time.strftime('%Y-%m-%d')} on {platform.node()} "
        f"({os.cpu_count()} cores), pyinfra over real SSH to systemd-nspawn hosts "
        "(see docs/sandbox.md). Written by `bench/noop_rerun.py`.",
        "",
        "| hosts | first run (s) | no-op re-run (s) | remote commands per host (median / max) "
        "| changed on re-run |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['hosts']} | {r['first_run_s']} | {r['noop_rerun_s']} | "
            f"{r['remote_commands_per_host']} / {r['remote_commands_max']} | "
            f"{r['noop_changed_operations']} |"
        )
    (RESULTS / "noop_rerun.md").write_text("\n".join(lines) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 4, 12])
    args = parser.parse_args()
    rows = []
    for size in args.sizes:
        rows.append(measure(size))
        print(json.dumps(rows[-1]), flush=True)
    write_results(rows)
    print(f"wrote {RESULTS / 'noop_rerun.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
