"""Benchmark: deploy.py's no-op re-run (wall time, remote commands, controller CPU) by class size.

For each size it boots a fresh sandbox instance, runs `pyinfra -y inventories/sandbox.py
deploy.py` once to converge it (the first run), then twice more as no-op re-runs (keeping
the faster), and records:

- remote commands per host on the no-op re-run (pyinfra's --debug log lines
  "Running command on <host>:", facts and operations alike), and one host's list of them;
- wall time of the no-op re-run, and of the first run where asked (`--first-run-sizes`);
- the controller's CPU seconds per host (user + system time of the pyinfra process, from
  getrusage of the child), for the no-op re-run and the first run;
- how many operations the re-run changed (must be 0).

Commands per host are deterministic: the headline. Wall and CPU times depend on the
machine and its load, which the results file records. Upstream requests and the apt
cache are another benchmark's subject.

Results go to bench/results/noop_rerun.md (the README links it) and .json. Needs root,
like the sandbox; uses the sandbox instance `ROSLAB_SANDBOX` (default roslab-bench) on
`ROSLAB_SANDBOX_SUBNET`, and takes it down after each size. Usage:

    .venv/bin/python bench/noop_rerun.py [--sizes 1 12 30] [--first-run-sizes 1 12]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
RESULTS = REPO / "bench" / "results"
INSTANCE = os.environ.get("ROSLAB_SANDBOX", "roslab-bench")
SUBNET = os.environ.get("ROSLAB_SANDBOX_SUBNET", "10.213.60.0/24")
COMMAND_LINE = re.compile(r"Running command on (\S+?): \(pty=\S+\) (.*)")
FACT_LINE = re.compile(r"\[(\S+?)\]\s+Loaded fact (\S+)(?: \((.*)\))?$", re.M)
MARKER_ARGUMENT = re.compile(r",? ?marker=[0-9a-f]+")
# Before roslab.probe (bench/results of 2026-11-21, commit 0adbf23): every no-op run.
BEFORE_COMMANDS_PER_HOST = 49


def bench_env() -> dict[str, str]:
    return {**os.environ, "ROSLAB_SANDBOX": INSTANCE, "ROSLAB_SANDBOX_SUBNET": SUBNET}


def sandbox(*args: str) -> None:
    subprocess.run([str(BIN / "roslab"), "sandbox", *args], check=True, env=bench_env(),
                   stdout=subprocess.DEVNULL)


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_deploy() -> dict:
    """Run deploy.py once: wall and CPU seconds, remote commands per host, changed operations."""
    cpu_before = children_cpu()
    started = time.monotonic()
    proc = subprocess.run(
        [str(BIN / "pyinfra"), "-y", "--json", "--debug", "inventories/sandbox.py", "deploy.py"],
        cwd=REPO, env=bench_env(), capture_output=True, text=True,
    )
    wall = time.monotonic() - started
    cpu = children_cpu() - cpu_before
    if proc.returncode != 0:
        raise SystemExit(f"deploy failed:\n{proc.stderr[-4000:]}")
    commands: dict[str, list[str]] = {}
    for host, command in COMMAND_LINE.findall(proc.stderr):
        commands.setdefault(host, []).append(command)
    facts: dict[str, list[str]] = {}
    for host, fact, arguments in FACT_LINE.findall(proc.stderr):
        arguments = MARKER_ARGUMENT.sub("", arguments or "").strip(", ")
        facts.setdefault(host, []).append(f"{fact} ({arguments})" if arguments else fact)
    return {"wall": wall, "cpu": cpu, "commands": commands, "facts": facts,
            "changed": changed_total(proc.stdout)}


def changed_total(json_output: str) -> int:
    """Operations that changed something, summed over hosts (pyinfra --json: 'success' lists them)."""
    results = json.loads(json_output)["results"]
    return sum(len(op["success"]) for op in results["operations"])


def measure(size: int, time_first_run: bool) -> dict:
    sandbox("down")
    sandbox("up", "--hosts", str(size))
    try:
        first = timed_deploy()
        noop = min((timed_deploy() for _ in range(2)), key=lambda run: run["wall"])
    finally:
        sandbox("down")
    per_host = sorted(len(commands) for commands in noop["commands"].values())
    example_host = sorted(noop["commands"])[0]
    row = {
        "hosts": size,
        "noop_commands_per_host_median": per_host[len(per_host) // 2] if per_host else 0,
        "noop_commands_per_host_max": max(per_host, default=0),
        "noop_wall_s": round(noop["wall"], 2),
        "noop_controller_cpu_s_per_host": round(noop["cpu"] / size, 3),
        "noop_changed_operations": noop["changed"],
        "first_run_wall_s": round(first["wall"], 1) if time_first_run else None,
        "first_run_controller_cpu_s_per_host": round(first["cpu"] / size, 2),
        "noop_commands_of_one_host": {
            "host": example_host,
            "commands": [shorten(command) for command in noop["commands"][example_host]],
            "facts": noop["facts"].get(example_host, []),
        },
    }
    return row


def shorten(command: str, width: int = 110) -> str:
    line = " ".join(command.split())
    return line if len(line) <= width else line[: width - 3] + "..."


def conditions() -> dict:
    return {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": platform.node(),
        "cores": os.cpu_count(),
        "load_average_1_5_15": [round(value, 2) for value in os.getloadavg()],
        "pyinfra": version("pyinfra"),
        "python": platform.python_version(),
    }


def write_results(rows: list[dict], started: dict, ended: dict, note: str) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    document = {"conditions": {"start": started, "end": ended, "note": note}, "rows": rows}
    (RESULTS / "noop_rerun.json").write_text(json.dumps(document, indent=2) + "\n")
    lines = [
        "# deploy.py on sandbox classrooms: no-op re-run, remote commands, controller CPU",
        "",
        f"Measured {started['date']} on {started['machine']} ({started['cores']} cores), pyinfra "
        f"{started['pyinfra']} over real SSH to systemd-nspawn hosts (see docs/sandbox.md). "
        "Written by `bench/noop_rerun.py`.",
        f"Load average (1/5/15 min) at the start {started['load_average_1_5_15']}, at the end "
        f"{ended['load_average_1_5_15']}. {note}".rstrip(),
        "",
        "Remote commands per host are deterministic (the headline); times depend on the "
        "machine and its load. Before roslab.probe every no-op run took "
        f"{BEFORE_COMMANDS_PER_HOST} remote commands per host.",
        "",
        "| hosts | no-op: remote commands per host (median / max) | no-op wall (s) "
        "| no-op controller CPU per host (s) | changed on re-run | first run wall (s) "
        "| first run controller CPU per host (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        first = "" if r["first_run_wall_s"] is None else r["first_run_wall_s"]
        lines.append(
            f"| {r['hosts']} | {r['noop_commands_per_host_median']} / {r['noop_commands_per_host_max']} "
            f"| {r['noop_wall_s']} | {r['noop_controller_cpu_s_per_host']} | {r['noop_changed_operations']} "
            f"| {first} | {r['first_run_controller_cpu_s_per_host']} |"
        )
    if rows:
        example = rows[-1]["noop_commands_of_one_host"]
        lines += ["", f"The no-op re-run's remote commands on {example['host']} "
                      f"({rows[-1]['hosts']}-host class):", ""]
        lines += [f"{index}. `{command}`" for index, command in enumerate(example["commands"], 1)]
        if example.get("facts"):
            lines += ["", "The facts they loaded (pyinfra's log; roslab.probe.HostProbe runs many "
                          "facts' commands in one):", ""]
            lines += [f"- `{fact}`" for fact in example["facts"]]
    (RESULTS / "noop_rerun.md").write_text("\n".join(lines) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 12, 30])
    parser.add_argument("--first-run-sizes", type=int, nargs="*", default=[1, 12],
                        help="sizes whose first run's wall time is reported")
    parser.add_argument("--note", default="", help="conditions worth recording (other load, ...)")
    args = parser.parse_args()
    started = conditions()
    rows = []
    for size in args.sizes:
        row = measure(size, size in args.first_run_sizes)
        rows.append(row)
        print(json.dumps({key: value for key, value in row.items() if key != "noop_commands_of_one_host"}),
              flush=True)
        write_results(rows, started, conditions(), args.note)  # a long run keeps what it measured
    print(f"wrote {RESULTS / 'noop_rerun.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
