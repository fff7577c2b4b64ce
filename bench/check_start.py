"""Benchmark: roslab's start-up against `pyinfra --version`, CPU-seconds, interleaved rounds.

Measured without contacting a host, on a 1-host roster (one main, the demo profile):

- `pyinfra --version`: pyinfra's own start-up, the floor (issue 41: within 20 % of it);
- `pyinfra inventories/lab.py debug-inventory`: pyinfra's CLI loading roslab's inventory (the
  roster read and checked, the profiles resolved): the start-up every deploy run pays before it
  connects; deploy.py's import and the facts of a no-op come on top and are not measured here;
- `roslab check`: the same roster and profiles through roslab's own command.

Each command runs once per round for every checkout in turn (the order alternates), so a shared
machine's load falls on all alike; the CPU of the child process tree (user + system, getrusage)
is what compares, the median per command is kept. `--baseline REF` also measures the git ref REF
(exported to a temporary folder, on PYTHONPATH before this checkout's installed roslab).
Results: bench/results/check_start.{md,json}.

    .venv/bin/python bench/check_start.py [--rounds 7] [--baseline main] [--note TEXT]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
RESULTS = REPO / "bench" / "results"
ROSTER = "classroom: {name: one}\nteams:\n  t1:\n    hosts:\n      t1-main: {role: main, address: 10.0.0.1}\n"


def commands(roster: Path) -> dict[str, list[str]]:
    return {"pyinfra --version": [str(BIN / "pyinfra"), "--version"],
            "pyinfra debug-inventory": [str(BIN / "pyinfra"), "inventories/lab.py", "debug-inventory"],
            "roslab check": [sys.executable, "-m", "roslab", "check", str(roster)]}


def cpu_of(command: list[str], checkout: Path, roster: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(checkout), "ROSLAB_ROSTER": str(roster)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(command, cwd=checkout, env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(checkouts: dict[str, Path], rounds: int, roster: Path) -> dict[str, dict[str, list[float]]]:
    runs = [(name, label, command) for name in checkouts for label, command in commands(roster).items()
            if name == "this" or label != "pyinfra --version"]
    cpu: dict[str, dict[str, list[float]]] = {name: {} for name in checkouts}
    for round_ in range(rounds):
        for name, label, command in (runs if round_ % 2 == 0 else runs[::-1]):
            cpu[name].setdefault(label, []).append(cpu_of(command, checkouts[name], roster))
    return cpu


def report(cpu: dict[str, dict[str, list[float]]], args) -> list[str]:
    floor = statistics.median(cpu["this"]["pyinfra --version"])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    lines = ["# roslab's start-up against `pyinfra --version`", "",
             f"Commit {commit}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {args.rounds} interleaved "
             f"rounds, 1-host roster, no host contacted (bench/check_start.py). {args.note}", "",
             "| checkout | command | median CPU-s | vs pyinfra --version | rounds (CPU-s) |", "|---|---|---:|---:|---|"]
    for name, labels in cpu.items():
        for label, values in labels.items():
            median = statistics.median(values)
            lines.append(f"| {name} | {label} | {median:.3f} | {median / floor:.2f}x | "
                         f"{', '.join(f'{v:.2f}' for v in values)} |")
    lines += ["", "The goal (issue 41): a 1-host no-op within 20 % of `pyinfra --version` (1.20x). "
              "`debug-inventory` is the part of that start-up before any host is contacted; "
              "deploy.py's import and the no-op's facts are not in it."]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--baseline", default="")
    parser.add_argument("--note", default="")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        roster = Path(folder) / "one.yaml"
        roster.write_text(ROSTER)
        checkouts = {"this": REPO}
        if args.baseline:
            checkouts[args.baseline] = Path(folder) / "baseline"
            checkouts[args.baseline].mkdir()
            subprocess.run(f"git archive {args.baseline} | tar -x -C {checkouts[args.baseline]}", shell=True,
                           cwd=REPO, check=True)
            subprocess.run([sys.executable, "-m", "compileall", "-q", "roslab", "deploy", "inventories"],
                           cwd=checkouts[args.baseline], check=True, stdout=subprocess.DEVNULL)
        cpu = measure(checkouts, args.rounds, roster)
    lines = report(cpu, args)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "check_start.json").write_text(json.dumps(
        {"rounds": args.rounds, "note": args.note, "machine": platform.machine(),
         "python": platform.python_version(), "cpu_seconds": cpu}, indent=2) + "\n")
    (RESULTS / "check_start.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
