"""Benchmark: a class's first run with and without shipping the underlay (issue 31).

A sandbox class on Jazzy whose robots all run the `esp32_microros` profile (the micro-ROS agent, built
from source in each robot's underlay), given fresh images, then one `pyinfra -y
inventories/sandbox.py deploy.py` per mode:

- shipping: the class as roslab runs it: the robots form one group, the first robot runs
  colcon, the controller ships its install tree to the others;
- without: each robot's underlay in a folder of its own (`sources_underlay_dir:
  ~/roslab_underlay_<host>`), so no two hosts share an install path and every robot builds
  (what every robot did before issue 31).

Recorded per mode: the first run's wall time, colcon runs (counted on the hosts: colcon keeps
one `log/build_*` folder per run in the underlay), and the bytes shipped (the packed tree
times the hosts that received it). The agent is the sandbox's stand-in unless the sandbox
serves the real one (ROSLAB_SANDBOX_SOURCES and ROSLAB_SANDBOX_ROS_RUNTIME): with stand-ins
the compile work saved is small and the wall times are dominated by the ROS install; the
colcon counts are what matters. Results go to bench/results/underlay_ship.md and .json
(underlay_ship_real.* with the real agent).
Needs root, like the sandbox; uses the sandbox instance `ROSLAB_SANDBOX` (default shipbench)
on `ROSLAB_SANDBOX_SUBNET` (default 10.213.66.0/24) and takes it down at the end. Usage:

    .venv/bin/python bench/underlay_ship.py [--hosts 4]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

BIN = Path(sys.executable).parent
RESULTS = REPO / "bench" / "results"
INSTANCE = os.environ.get("ROSLAB_SANDBOX", "shipbench")
SUBNET = os.environ.get("ROSLAB_SANDBOX_SUBNET", "10.213.66.0/24")
STATE_DIR = Path("/run/roslab/sandbox") / INSTANCE


def bench_env() -> dict[str, str]:
    # every team on 24.04 (Jazzy): one distro, so all the robots are one group
    return {"ROSLAB_SANDBOX_RELEASES": "24.04", **os.environ, "ROSLAB_SANDBOX": INSTANCE,
            "ROSLAB_SANDBOX_SUBNET": SUBNET}


def sandbox(*args: str, capture: bool = False) -> str:
    done = subprocess.run([str(BIN / "roslab"), "sandbox", *args], check=True, env=bench_env(),
                          stdout=subprocess.PIPE if capture else subprocess.DEVNULL, text=True)
    return done.stdout or ""


def write_roster(original: dict, ship: bool, cache_dir: Path) -> list[str]:
    """The sandbox roster with every team's robot on esp32_microros; the robots' names."""
    roster = json.loads(json.dumps(original))
    roster["classroom"]["sources_cache_dir"] = str(cache_dir)
    robots = []
    for team in roster["teams"].values():
        team.update(robot_profile="esp32_microros", esp32_usb_serial="0001A2B3", esp32_attached_to="robot",
                    esp32_transport="udp", esp32_present=False)
        for name, host in team["hosts"].items():
            if host.get("role") == "robot":
                robots.append(name)
                if not ship:
                    host["sources_underlay_dir"] = f"~/roslab_underlay_{name.replace('-', '_')}"
    (STATE_DIR / "roster.yaml").write_text(yaml.safe_dump(roster, sort_keys=False))
    return robots


def colcon_runs(host: str, ship: bool) -> int:
    folder = "roslab_underlay" if ship else f"roslab_underlay_{host.replace('-', '_')}"
    out = sandbox("ssh", host, f"ls -d ~/{folder}/log/build_* 2>/dev/null | wc -l", capture=True)
    return int(out.split()[-1])


def first_run(original: dict, hosts: list[str], ship: bool, cache_dir: Path) -> dict:
    sandbox("reset", *hosts)
    shutil.rmtree(cache_dir / "underlays", ignore_errors=True)  # the class's first build
    robots = write_roster(original, ship, cache_dir)
    load = os.getloadavg()[0]
    started = time.monotonic()
    proc = subprocess.run([str(BIN / "pyinfra"), "-y", "inventories/sandbox.py", "deploy.py"],
                          cwd=REPO, env=bench_env(), capture_output=True, text=True)
    wall = time.monotonic() - started
    if proc.returncode != 0:
        raise SystemExit(f"deploy failed (shipping {ship}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    runs = {robot: colcon_runs(robot, ship) for robot in robots}
    kept = sorted((cache_dir / "underlays").glob("*.tar.gz"))
    receivers = sum(1 for count in runs.values() if count == 0)
    packed = sum(path.stat().st_size for path in kept)
    return {"shipping": ship, "hosts": len(hosts), "robots": len(robots), "wall_s": round(wall, 1),
            "load_before": round(load, 1), "colcon_runs": runs, "colcon_total": sum(runs.values()),
            "packed_bytes": packed, "shipped_bytes": packed * receivers}


def markdown(runs: list[dict], machine: dict) -> str:
    lines = [
        "# First run with and without shipping the underlay",
        "",
        "`bench/underlay_ship.py`: a sandbox class whose robots run `esp32_microros` (the micro-ROS agent "
        "built from source), given fresh images, one `pyinfra -y inventories/sandbox.py deploy.py` per mode. "
        "Without shipping, each robot's underlay has its own install path, so every robot builds.",
        "",
        "| shipping | hosts | robots | first run (s) | colcon runs (robots) | packed tree (KB) | bytes shipped (KB) "
        "| load before |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        lines.append(f"| {'on' if run['shipping'] else 'off'} | {run['hosts']} | {run['robots']} | {run['wall_s']:.0f} "
                     f"| {run['colcon_total']} | {run['packed_bytes'] / 1e3:.0f} | {run['shipped_bytes'] / 1e3:.0f} "
                     f"| {run['load_before']} |")
    lines += [
        "",
        f"Machine: {machine['cpus']} CPUs, {machine['platform']}, Python {machine['python']}; measured "
        f"{machine['date']} while other work shared the machine (load average before each run), so wall "
        f"times are noisy; the colcon counts are not. Agent: {machine['agent']}.",
        "",
        "Shipping leaves one colcon run per group: the class's compile work is one host's. With the "
        "stand-in agent that work is seconds, so the first run's wall time is the ROS install's (and the "
        "machine's load); with the real agent it is many minutes per robot, which the receivers no longer "
        "spend.",
        "",
    ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hosts", type=int, default=4)
    args = parser.parse_args()
    sandbox("down")
    sandbox("up", "--hosts", str(args.hosts))
    runs = []
    try:
        original = yaml.safe_load((STATE_DIR / "roster.yaml").read_text())
        hosts = [name for team in original["teams"].values() for name in team["hosts"]]
        cache_dir = STATE_DIR / "bench-sources-cache"  # inside the roster's folder, as a cache must be
        for ship in (False, True):
            run = first_run(original, hosts, ship, cache_dir)
            print(json.dumps(run), flush=True)
            runs.append(run)
    finally:
        sandbox("down")
    real = bool(os.environ.get("ROSLAB_SANDBOX_SOURCES")) and bool(os.environ.get("ROSLAB_SANDBOX_ROS_RUNTIME"))
    machine = {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "agent": "the real micro-ROS agent" if real else "the sandbox's stand-in (no real sources)"}
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = "underlay_ship_real" if real else "underlay_ship"
    (RESULTS / f"{name}.json").write_text(json.dumps({"machine": machine, "runs": runs}, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(markdown(runs, machine))
    print(markdown(runs, machine))
    return 0


if __name__ == "__main__":
    sys.exit(main())
