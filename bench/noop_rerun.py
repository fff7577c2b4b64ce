"""Benchmark: deploy.py's no-op re-run on 1, 4 and 12 hosts, interleaved: controller CPU per host.

It boots one sandbox instance per class size (`<prefix>-<size>`), converges each with one
run of `pyinfra -y inventories/sandbox.py deploy.py` (the first run), then measures no-op
re-runs of every variant on every size in turn, round after round (the order of the
variants alternates), so that the machine's load, which changes by the minute on a shared
machine, falls on all of them alike. Variants:

- `roslab`: this checkout;
- `pyinfra-order`: this checkout with `ROSLAB_PYINFRA_PLANNING=pyinfra`, the diagnostic switch
  that keeps pyinfra's own operation order from `inspect.stack()` (roslab.pyinfra_planning);
- `baseline`: the git ref `--baseline` (default `main`) exported to a temporary folder and run
  from there, roslab and deploy.py both (omit with `--baseline ''`).

For each size and variant it records the controller's CPU seconds (user + system of the
pyinfra process and its children, from getrusage; the median of the rounds) per host, the
wall time, and from one `--debug` run per size and variant, the remote commands per host
(pyinfra's "Running command on <host>:" lines) and the operations changed (must be 0).
From these: the 12-host / 1-host CPU ratio per variant, and the CPU per host against the
baseline. Then it profiles one no-op re-run of the largest class per variant
(bench/profile_noop.py, on CPU time): CPU per pyinfra stage, the operation order's share,
CPU by package and the costliest functions: where the CPU goes.

CPU, not wall time, is what compares: wall time on a shared machine is mostly waiting.
Results go to bench/results/noop_rerun.md (the README links it) and .json. Needs root,
like the sandbox. The instances are `$ROSLAB_BENCH_SANDBOX-<size>` (default prefix
roslab-bench) on the subnets `$ROSLAB_BENCH_SUBNETS` (comma-separated, one per size, in
the order of --sizes); they are taken down at the end unless --keep. Usage:

    .venv/bin/python bench/noop_rerun.py [--sizes 1 4 12] [--rounds 3] [--baseline main] [--note TEXT]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from importlib.metadata import version
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
RESULTS = REPO / "bench" / "results"
PREFIX = os.environ.get("ROSLAB_BENCH_SANDBOX", "roslab-bench")
SUBNETS = os.environ.get("ROSLAB_BENCH_SUBNETS", "10.213.60.0/24,10.213.61.0/24,10.213.62.0/24").split(",")
OP_ORDER_SWITCH = "ROSLAB_PYINFRA_PLANNING"  # roslab.pyinfra_planning.SWITCH
COMMAND_LINE = re.compile(r"Running command on (\S+?): \(pty=\S+\) (.*)")
FACT_LINE = re.compile(r"\[(\S+?)\]\s+Loaded fact (\S+)(?: \((.*)\))?$", re.M)
MARKER_ARGUMENT = re.compile(r",? ?marker=[0-9a-f]+")
PYINFRA_RUN = ["-y", "--json", "inventories/sandbox.py", "deploy.py"]
# Before roslab.probe (bench/results of 2026-11-21, commit 0adbf23): every no-op run.
BEFORE_COMMANDS_PER_HOST = 49


class Variant:
    def __init__(self, name: str, checkout: Path, env: dict[str, str], what: str):
        self.name, self.checkout, self.env, self.what = name, checkout, env, what


class Instance:
    def __init__(self, size: int, subnet: str):
        self.size, self.name, self.subnet = size, f"{PREFIX}-{size}", subnet

    def env(self, variant: Variant) -> dict[str, str]:
        env = {key: value for key, value in os.environ.items() if key != OP_ORDER_SWITCH}
        return {**env, **variant.env, "ROSLAB_SANDBOX": self.name, "ROSLAB_SANDBOX_SUBNET": self.subnet}

    def sandbox(self, *args: str) -> None:
        env = {**os.environ, "ROSLAB_SANDBOX": self.name, "ROSLAB_SANDBOX_SUBNET": self.subnet}
        subprocess.run([str(BIN / "roslab"), "sandbox", *args], check=True, env=env, stdout=subprocess.DEVNULL)


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_deploy(instance: Instance, variant: Variant, debug: bool = False) -> dict:
    """deploy.py once: wall and CPU seconds, changed operations; with debug, commands per host."""
    command = [str(BIN / "pyinfra"), *(["--debug"] if debug else []), *PYINFRA_RUN]
    cpu_before = children_cpu()
    started = time.monotonic()
    proc = subprocess.run(command, cwd=variant.checkout, env=instance.env(variant), capture_output=True, text=True)
    wall = time.monotonic() - started
    cpu = children_cpu() - cpu_before
    if proc.returncode != 0:
        raise SystemExit(f"deploy failed ({variant.name}, {instance.name}):\n{proc.stderr[-4000:]}")
    result = {"wall": wall, "cpu": cpu, "changed": changed_total(proc.stdout)}
    if debug:
        commands: dict[str, list[str]] = {}
        for host, line in COMMAND_LINE.findall(proc.stderr):
            commands.setdefault(host, []).append(line)
        facts: dict[str, list[str]] = {}
        for host, fact, arguments in FACT_LINE.findall(proc.stderr):
            arguments = MARKER_ARGUMENT.sub("", arguments or "").strip(", ")
            facts.setdefault(host, []).append(f"{fact} ({arguments})" if arguments else fact)
        result.update(commands=commands, facts=facts)
    return result


def changed_total(json_output: str) -> int:
    """Operations that changed something, summed over hosts (pyinfra --json: 'success' lists them)."""
    results = json.loads(json_output)["results"]
    return sum(len(op["success"]) for op in results["operations"])


def profile(instance: Instance, variant: Variant, out: Path) -> dict:
    """One no-op re-run under bench/profile_noop.py: where the controller's CPU goes."""
    subprocess.run([sys.executable, str(REPO / "bench" / "profile_noop.py"), "--out", str(out), "--top", "15",
                    "--", *PYINFRA_RUN], cwd=variant.checkout, env=instance.env(variant), check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads(out.read_text())


@contextmanager
def baseline_checkout(ref: str):
    """The git ref's files in a temporary folder (roslab, deploy.py, inventories), or None."""
    if not ref:
        yield None
        return
    with tempfile.TemporaryDirectory(prefix="roslab-bench-baseline-") as folder:
        archive = subprocess.run(["git", "-C", str(REPO), "archive", ref], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", ref], check=True,
                                capture_output=True, text=True).stdout.strip()
        yield Path(folder), commit


def compiled(checkout: Path) -> None:
    """Byte-compile a checkout's modules, as installing roslab does: pyinfra's CLI writes no
    .pyc files, so a checkout never run otherwise compiles its modules on every run."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", *(str(checkout / name) for name in
                                                                ("roslab", "deploy", "inventories"))],
                   check=True, stdout=subprocess.DEVNULL)


def variants_for(baseline) -> list[Variant]:
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    variants = [
        Variant("roslab", REPO, {}, f"this checkout ({head})"),
        Variant("pyinfra-order", REPO, {OP_ORDER_SWITCH: "pyinfra"},
                f"this checkout ({head}) with {OP_ORDER_SWITCH}=pyinfra"),
    ]
    if baseline is not None:
        folder, commit = baseline
        # Before the editable install of this checkout on sys.path: the baseline's own roslab.
        variants.append(Variant("baseline", folder, {"PYTHONPATH": str(folder)}, f"{commit}, exported"))
        check = subprocess.run([sys.executable, "-c", "import roslab; print(roslab.__file__)"], cwd=folder,
                               env={**os.environ, "PYTHONPATH": str(folder)}, capture_output=True, text=True)
        if not check.stdout.startswith(str(folder)):
            raise SystemExit(f"the baseline would not run its own roslab: {check.stdout or check.stderr}")
    return variants


def conditions() -> dict:
    return {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": platform.node(),
        "cores": os.cpu_count(),
        "load_average_1_5_15": [round(value, 2) for value in os.getloadavg()],
        "pyinfra": version("pyinfra"),
        "python": platform.python_version(),
    }


def shorten(command: str, width: int = 110) -> str:
    line = " ".join(command.split())
    return line if len(line) <= width else line[: width - 3] + "..."


def summarise(sizes, variants, first_runs, checks, samples, profiles) -> dict:
    rows = []
    for size in sizes:
        for variant in variants:
            cpu = samples[(size, variant.name)]
            check = checks[(size, variant.name)]
            per_host = sorted(len(commands) for commands in check["commands"].values())
            rows.append({
                "hosts": size, "variant": variant.name,
                "noop_cpu_s_median": round(statistics.median(cpu["cpu"]), 3),
                "noop_cpu_s_per_host": round(statistics.median(cpu["cpu"]) / size, 3),
                "noop_cpu_s_samples": [round(value, 3) for value in cpu["cpu"]],
                "noop_wall_s_median": round(statistics.median(cpu["wall"]), 2),
                "noop_commands_per_host_max": max(per_host, default=0),
                "noop_commands_per_host_min": min(per_host, default=0),
                "noop_changed_operations": max([check["changed"], *cpu["changed"]]),
            })
    by = {(row["hosts"], row["variant"]): row for row in rows}
    small, large = min(sizes), max(sizes)
    ratios = {variant.name: round(by[(large, variant.name)]["noop_cpu_s_median"]
                                  / by[(small, variant.name)]["noop_cpu_s_median"], 2) for variant in variants}
    against = "baseline" if any(variant.name == "baseline" for variant in variants) else "pyinfra-order"
    per_host_gain = {size: round(by[(size, against)]["noop_cpu_s_per_host"]
                                 / by[(size, "roslab")]["noop_cpu_s_per_host"], 2) for size in sizes}
    # What each host beyond the first adds: the slope between the smallest and largest class.
    per_extra_host = {variant.name: round((by[(large, variant.name)]["noop_cpu_s_median"]
                                           - by[(small, variant.name)]["noop_cpu_s_median"]) / (large - small), 3)
                      for variant in variants} if large > small else {}
    example = checks[(large, "roslab")]
    example_host = sorted(example["commands"])[0] if example["commands"] else ""
    return {
        "variants": {variant.name: variant.what for variant in variants},
        "rows": rows,
        "cpu_ratio_largest_to_smallest": {"sizes": [large, small], **ratios},
        "cpu_per_host_gain_against": against,
        "cpu_per_host_gain": per_host_gain,
        "cpu_s_per_extra_host": per_extra_host,
        "cpu_per_extra_host_gain": (round(per_extra_host[against] / per_extra_host["roslab"], 2)
                                    if per_extra_host.get("roslab", 0) > 0 else None),
        "first_runs": first_runs,
        "profiles": profiles,
        "noop_commands_of_one_host": {
            "host": example_host, "hosts": large,
            "commands": [shorten(command) for command in example["commands"].get(example_host, [])],
            "facts": example["facts"].get(example_host, []),
        },
    }


def write_results(document: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "noop_rerun.json").write_text(json.dumps(document, indent=2) + "\n")
    (RESULTS / "noop_rerun.md").write_text("\n".join(markdown(document)) + "\n")


def markdown(document: dict) -> list[str]:
    start, end, note = (document["conditions"][key] for key in ("start", "end", "note"))
    result = document["result"]
    large, small = result["cpu_ratio_largest_to_smallest"]["sizes"]
    lines = [
        "# deploy.py's no-op re-run: controller CPU by class size, interleaved",
        "",
        f"Measured {start['date']} on {start['machine']} ({start['cores']} cores), pyinfra {start['pyinfra']}, "
        f"Python {start['python']}, over real SSH to systemd-nspawn hosts (see docs/sandbox.md); "
        f"{document['rounds']} rounds, every variant on every size in each round. Written by "
        "`bench/noop_rerun.py`.",
        f"Load average (1/5/15 min) at the start {start['load_average_1_5_15']}, at the end "
        f"{end['load_average_1_5_15']}. {note}".rstrip(),
        "",
        "Variants: " + "; ".join(f"`{name}`: {what}" for name, what in result["variants"].items()) + ".",
        "",
        "CPU is the pyinfra process's user + system time (the median of the rounds): what compares on a "
        "shared machine. Wall time there is mostly waiting and is given for scale only. Remote commands "
        "and changes come from one `--debug` run per size and variant. Before roslab.probe every no-op "
        f"run took {BEFORE_COMMANDS_PER_HOST} remote commands per host.",
        "",
        "| hosts | variant | no-op controller CPU (s) | CPU per host (s) | rounds' CPU (s) | wall (s) "
        "| remote commands per host (min / max) | changed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        lines.append(
            f"| {row['hosts']} | {row['variant']} | {row['noop_cpu_s_median']} | {row['noop_cpu_s_per_host']} "
            f"| {', '.join(str(value) for value in row['noop_cpu_s_samples'])} | {row['noop_wall_s_median']} "
            f"| {row['noop_commands_per_host_min']} / {row['noop_commands_per_host_max']} "
            f"| {row['noop_changed_operations']} |")
    ratios = result["cpu_ratio_largest_to_smallest"]
    lines += ["", f"CPU of the {large}-host no-op over the {small}-host one: "
              + ", ".join(f"{name} {value}×" for name, value in ratios.items() if name != "sizes") + ".",
              f"CPU per host, {result['cpu_per_host_gain_against']} over roslab: "
              + ", ".join(f"{size} hosts {gain}×" for size, gain in result["cpu_per_host_gain"].items()) + "."]
    if result["cpu_s_per_extra_host"]:
        lines += [f"CPU per extra host (the slope from {small} to {large} hosts, s): "
                  + ", ".join(f"{name} {value}" for name, value in result["cpu_s_per_extra_host"].items())
                  + f"; {result['cpu_per_host_gain_against']} over roslab {result['cpu_per_extra_host_gain']}×."]
    first = result["first_runs"]
    if first:
        lines += ["", "First runs (converging fresh instances, this checkout): "
                  + ", ".join(f"{run['hosts']} hosts {run['wall_s']} s wall, {run['cpu_s_per_host']} CPU-s per host"
                              for run in first) + "."]
    lines += ["", f"## Where the CPU goes ({large}-host no-op, one profiled run per variant)", "",
              "bench/profile_noop.py: cProfile on CPU time (its overhead included, alike for all variants); "
              "pyinfra's stages: Setup (inventory, roster), Connect (SSH), Prepare (deploy.py once per host, "
              "facts), Execute (operations), Disconnect.", ""]
    for name, summary in result["profiles"].items():
        stages = ", ".join(f"{stage} {seconds}" for stage, seconds in summary["stages"].items())
        order = "; ".join(f"{which}'s function: {value['calls']} calls, {value['cpu_s']} s "
                          f"({round(100 * value['share'])} %)" for which, value in summary["operation_order"].items())
        packages = ", ".join(f"{package} {seconds}" for package, seconds in list(summary["by_package"].items())[:8])
        lines += [f"**{name}**: {summary['cpu_s']} CPU-s profiled. Stages (s): {stages}.",
                  f"Operation order ({order or 'not called'}).", f"Self CPU by package (s): {packages}.",
                  "Costliest functions, self CPU: "
                  + "; ".join(f"`{entry['function']}` {entry['self_s']} s ({entry['calls']} calls)"
                              for entry in summary["top_self"][:8]) + ".", ""]
    example = result["noop_commands_of_one_host"]
    if example["commands"]:
        lines += [f"The no-op re-run's remote commands on {example['host']} ({example['hosts']}-host class):", ""]
        lines += [f"{index}. `{command}`" for index, command in enumerate(example["commands"], 1)]
    if example["facts"]:
        lines += ["", "The facts they loaded (pyinfra's log; roslab.probe.HostProbe runs many facts' commands in one):",
                  ""]
        lines += [f"- `{fact}`" for fact in example["facts"]]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 4, 12])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--baseline", default="main", help="git ref measured as `baseline` ('' for none)")
    parser.add_argument("--keep", action="store_true", help="leave the instances up (converged)")
    parser.add_argument("--note", default="", help="conditions worth recording (other load, ...)")
    args = parser.parse_args()
    if len(SUBNETS) < len(args.sizes):
        raise SystemExit(f"ROSLAB_BENCH_SUBNETS names {len(SUBNETS)} subnets for {len(args.sizes)} sizes")
    instances = [Instance(size, subnet.strip()) for size, subnet in zip(args.sizes, SUBNETS)]
    started = conditions()
    with baseline_checkout(args.baseline) as baseline:
        variants = variants_for(baseline)
        for checkout in {variant.checkout for variant in variants}:
            compiled(checkout)
        this_checkout = variants[0]
        first_runs = []
        try:
            for instance in instances:
                fresh = not Path(f"/run/roslab/sandbox/{instance.name}/roster.yaml").exists()
                instance.sandbox("up", "--hosts", str(instance.size))
                first = run_deploy(instance, this_checkout)
                if fresh:
                    first_runs.append({"hosts": instance.size, "wall_s": round(first["wall"], 1),
                                       "cpu_s_per_host": round(first["cpu"] / instance.size, 2)})
                print(f"{instance.name}: converged", flush=True)
            checks = {(instance.size, variant.name): run_deploy(instance, variant, debug=True)
                      for instance in instances for variant in variants}
            samples = {(instance.size, variant.name): {"cpu": [], "wall": [], "changed": []}
                       for instance in instances for variant in variants}
            for round_index in range(args.rounds):
                for instance in instances:
                    for variant in (variants if round_index % 2 == 0 else variants[::-1]):
                        run = run_deploy(instance, variant)
                        sample = samples[(instance.size, variant.name)]
                        for key in ("cpu", "wall", "changed"):
                            sample[key].append(run[key])
                        print(json.dumps({"round": round_index + 1, "hosts": instance.size,
                                          "variant": variant.name, "cpu_s": round(run["cpu"], 3),
                                          "changed": run["changed"]}), flush=True)
            profiles = {}
            with tempfile.TemporaryDirectory() as folder:
                for variant in variants:
                    profiles[variant.name] = profile(instances[-1], variant, Path(folder) / f"{variant.name}.json")
        finally:
            if not args.keep:
                for instance in instances:
                    instance.sandbox("down")
    result = summarise(args.sizes, variants, first_runs, checks, samples, profiles)
    write_results({"conditions": {"start": started, "end": conditions(), "note": args.note},
                   "rounds": args.rounds, "result": result})
    print(json.dumps({key: result[key] for key in ("cpu_ratio_largest_to_smallest", "cpu_per_host_gain",
                                                   "cpu_s_per_extra_host", "cpu_per_extra_host_gain")}))
    print(f"wrote {RESULTS / 'noop_rerun.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
