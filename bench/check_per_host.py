"""Benchmark: `roslab check` CPU per host, the check of 10,000 hosts minus that of 10.

Two rosters (teams of 100 hosts, a main and robots, addresses 10.x.y.z; 10 hosts: one team)
are written to a temporary folder and `roslab check` runs on each in turn, round after
round (interleaved, so the load of a shared machine falls on both alike). CPU seconds of
the child process (user + system, getrusage) are what compare; the median per size is kept.
Per host = (median(10,000) - median(10)) / 9,990. Results: bench/results/check_per_host.{md,json}.

    .venv/bin/python bench/check_per_host.py [--rounds 5] [--note TEXT] [--profile] [--baseline REF]

--baseline REF also measures the git ref REF (exported to a temporary folder, run from there)
in the same interleaved rounds, so both figures share the machine's load.

--profile also writes the 25 costliest functions (cProfile, cumulative) of one 10,000-host check.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "results"
SIZES = (10, 10_000)


def roster(hosts: int) -> str:
    teams, left, team = [], hosts, 0
    while left:
        count = min(100, left)
        lines = "\n".join(f"      t{team}-h{host}: {{role: {'main' if host == 0 else 'robot'}, "
                          f"address: 10.{team // 250}.{team % 250}.{host + 1}}}" for host in range(count))
        teams.append(f"  t{team}:\n    ros_domain_id: {team}\n    hosts:\n{lines}")
        left, team = left - count, team + 1
    return "classroom: {name: bench}\nteams:\n" + "\n".join(teams) + "\n"


def cpu_of(command: list[str], cwd: Path = REPO) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, cwd=cwd)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def profile(path: Path) -> str:
    out = subprocess.run([sys.executable, "-c", (
        "import cProfile, pstats, io, sys\n"
        "from roslab.cli.main import main\n"
        "prof = cProfile.Profile(); prof.enable()\n"
        f"main(['check', {str(path)!r}])\n"
        "prof.disable(); buf = io.StringIO()\n"
        "pstats.Stats(prof, stream=buf).sort_stats('cumulative').print_stats(25)\n"
        "sys.stderr.write(buf.getvalue())\n")], cwd=REPO, capture_output=True, text=True, check=True)
    return out.stderr


def measure(checkouts: dict[str, Path], rounds: int, folder: Path) -> dict[str, dict[int, list[float]]]:
    """CPU-seconds of `roslab check` per checkout and size, interleaved round after round."""
    paths = {size: folder / f"lab-{size}.yaml" for size in SIZES}
    for size, path in paths.items():
        path.write_text(roster(size))
    cpu = {name: {size: [] for size in SIZES} for name in checkouts}
    runs = [(name, size) for name in checkouts for size in SIZES]
    for round_ in range(rounds):
        for name, size in (runs if round_ % 2 == 0 else runs[::-1]):
            cpu[name][size].append(cpu_of([sys.executable, "-m", "roslab", "check", str(paths[size])],
                                          checkouts[name]))
    return cpu


def per_host(values: dict[int, list[float]]) -> float:
    small, large = (statistics.median(values[size]) for size in SIZES)
    return (large - small) / (SIZES[1] - SIZES[0]) * 1000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--note", default="")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--baseline", default="")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        checkouts = {"this": REPO}
        if args.baseline:
            checkouts[args.baseline] = Path(folder) / "baseline"
            checkouts[args.baseline].mkdir()
            subprocess.run(f"git archive {args.baseline} | tar -x -C {checkouts[args.baseline]}", shell=True,
                           cwd=REPO, check=True)
        cpu = measure(checkouts, args.rounds, Path(folder))
        profiled = profile(Path(folder) / f"lab-{SIZES[-1]}.yaml") if args.profile else ""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    result = {"commit": commit, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "machine": platform.machine(), "python": platform.python_version(), "rounds": args.rounds,
              "cpu_seconds": {name: {str(size): v for size, v in values.items()} for name, values in cpu.items()},
              "per_host_ms": {name: round(per_host(values), 3) for name, values in cpu.items()}, "note": args.note}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "check_per_host.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = ["# `roslab check`: CPU per host", "",
             f"Commit {commit}, {result['date']}, {args.rounds} interleaved rounds (bench/check_per_host.py). "
             + args.note, "", "| checkout | hosts | median CPU-s | rounds (CPU-s) |", "|---|---:|---:|---|"]
    lines += [f"| {name} | {size} | {statistics.median(values[size]):.3f} | "
              f"{', '.join(f'{v:.2f}' for v in values[size])} |" for name, values in cpu.items() for size in SIZES]
    lines += [""] + [f"**{name}: {per_host(values):.3f} ms per host** (check of {SIZES[1]:,} hosts minus that of "
                     f"{SIZES[0]}, over {SIZES[1] - SIZES[0]:,})." for name, values in cpu.items()]
    lines += ["", "The goal (issue 41): at most 0.35 ms per host."]
    if profiled:
        lines += ["", "## Profile of one 10,000-host check (cumulative)", "", "```", profiled.strip(), "```"]
    (RESULTS / "check_per_host.md").write_text("\n".join(lines) + "\n")
    print("\n".join(line for line in lines if not line.startswith("```")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
