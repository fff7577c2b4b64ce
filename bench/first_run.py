"""Benchmark: deploy.py's first run with and without the classroom's apt cache, by class size.

For each size it boots a sandbox instance and, for each mode (no cache, then the cache on
team1-main: `apt_cache_host` in the roster), gives every host a fresh image (the cache host's
cache too), runs `pyinfra -y inventories/sandbox.py deploy.py` once and records:

- the first run's wall time (and the controller's CPU seconds);
- what the class fetched from upstream, from the sandbox upstream's request log: requests
  and bytes in all, and .deb requests against distinct .debs (the cache's point: each .deb
  once for the class, not once per host).

The first host of each release fills the cache before the class installs, so no two hosts
miss the same file in the same instant, and apt-cacher-ng stores each .deb once. The upstream
can still see a few .debs asked for twice within milliseconds: apt-cacher-ng sometimes closes
a client connection just as apt sends its next request, abandons the transfer it had started
for it and fetches the file again when apt asks anew (seen with nginx as the upstream too).
So `.deb requests` may exceed `distinct .debs` by a few from run to run, and the bytes include
those abandoned transfers; wall times depend on the machine and its load, which the results
file records. Results go to bench/results/first_run.md (the README links
it) and .json. Needs root, like the sandbox; uses the sandbox instance `ROSLAB_SANDBOX`
(default cache) on `ROSLAB_SANDBOX_SUBNET` (default 10.213.65.0/24) and takes it down after
each size. Usage:

    .venv/bin/python bench/first_run.py [--sizes 1 12]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from roslab.sandbox import upstream  # noqa: E402

BIN = Path(sys.executable).parent
RESULTS = REPO / "bench" / "results"
INSTANCE = os.environ.get("ROSLAB_SANDBOX", "cache")
SUBNET = os.environ.get("ROSLAB_SANDBOX_SUBNET", "10.213.65.0/24")
STATE_DIR = Path("/run/roslab/sandbox") / INSTANCE
CACHE_HOST = "team1-main"


def bench_env() -> dict[str, str]:
    return {**os.environ, "ROSLAB_SANDBOX": INSTANCE, "ROSLAB_SANDBOX_SUBNET": SUBNET}


def sandbox(*args: str) -> None:
    subprocess.run([str(BIN / "roslab"), "sandbox", *args], check=True, env=bench_env(),
                   stdout=subprocess.DEVNULL)


def set_cache(on: bool) -> None:
    roster_path = STATE_DIR / "roster.yaml"
    roster = yaml.safe_load(roster_path.read_text())
    if on:
        roster["classroom"]["apt_cache_host"] = CACHE_HOST
    else:
        roster["classroom"].pop("apt_cache_host", None)
    roster_path.write_text(yaml.safe_dump(roster, sort_keys=False))


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def first_run(size: int, cache: bool) -> dict:
    hosts = [f"team{index // 2 + 1}-{('main', 'robot')[index % 2]}" for index in range(size)]
    sandbox("reset", *hosts)
    set_cache(cache)
    log = STATE_DIR / upstream.REQUEST_LOG
    start = len(upstream.read_requests(log))
    load = os.getloadavg()[0]
    cpu_before = children_cpu()
    started = time.monotonic()
    proc = subprocess.run([str(BIN / "pyinfra"), "-y", "inventories/sandbox.py", "deploy.py"],
                          cwd=REPO, env=bench_env(), capture_output=True, text=True)
    wall = time.monotonic() - started
    cpu = children_cpu() - cpu_before
    if proc.returncode != 0:
        raise SystemExit(f"deploy failed ({size} hosts, cache {cache}):\n{proc.stdout[-4000:]}")
    fetched = upstream.read_requests(log)[start:]
    debs = [request for request in fetched if request.path.endswith(".deb")]
    return {
        "hosts": size, "cache": cache, "wall_s": round(wall, 1), "controller_cpu_s": round(cpu, 1),
        "load_before": round(load, 1),
        "requests": len(fetched), "bytes": sum(request.bytes for request in fetched),
        "deb_requests": len(debs), "distinct_debs": len({request.path for request in debs}),
        "deb_bytes": sum(request.bytes for request in debs),
        "clients": sorted({request.client for request in fetched}),
    }


def markdown(runs: list[dict], machine: dict) -> str:
    lines = [
        "# First run with and without the classroom's apt cache",
        "",
        "`bench/first_run.py`: a sandbox class given fresh images, then one `pyinfra -y "
        "inventories/sandbox.py deploy.py`; without the cache, then with `apt_cache_host: team1-main`. "
        "Upstream figures come from the sandbox upstream's request log (every request, its status "
        "and bytes). The packages are the sandbox's: real Debian packages (rosdep, colcon, ...) and "
        "stand-in ROS packages, so the bytes are smaller than a real ROS 2 install; the counts are "
        "what matters.",
        "",
        "| hosts | apt cache | first run (s) | upstream requests | upstream MB | .deb requests | distinct .debs "
        "| .deb requests per distinct .deb | load before |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        per = run["deb_requests"] / run["distinct_debs"] if run["distinct_debs"] else 0
        lines.append(
            f"| {run['hosts']} | {'on' if run['cache'] else 'off'} | {run['wall_s']:.0f} | {run['requests']} | "
            f"{run['bytes'] / 1e6:.1f} | {run['deb_requests']} | {run['distinct_debs']} | {per:.2f} | "
            f"{run['load_before']} |")
    lines += [
        "",
        f"Machine: {machine['cpus']} CPUs, {machine['platform']}, Python {machine['python']}; "
        f"measured {machine['date']} while other work shared the machine (load average before each run in "
        "the table), so wall times are noisy; request and byte counts are not.",
        "",
        "With the cache every .deb is fetched from upstream by the cache host only: the first host of each "
        "release updates and downloads first, and the class installs from the cache. "
        + ("Every .deb was requested upstream exactly once in these runs." if all(
            r["deb_requests"] == r["distinct_debs"] for r in runs if r["cache"]) else
           "The few .debs requested more than once (see the table) are apt-cacher-ng's retries of transfers "
           "it abandoned when it closed a client connection as apt sent its next request; it stores each "
           ".deb once (its own log), and the abandoned transfers count in the bytes.")
        + " rosdep's data is fetched by the controller, once per file per run, in both modes.",
        "",
    ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 12])
    args = parser.parse_args()
    runs = []
    for size in args.sizes:
        sandbox("down")
        sandbox("up", "--hosts", str(size))
        try:
            for cache in (False, True):
                run = first_run(size, cache)
                print(json.dumps(run), flush=True)
                runs.append(run)
        finally:
            sandbox("down")
    machine = {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "first_run.json").write_text(json.dumps({"machine": machine, "runs": runs}, indent=2) + "\n")
    (RESULTS / "first_run.md").write_text(markdown(runs, machine))
    print(markdown(runs, machine))
    return 0


if __name__ == "__main__":
    sys.exit(main())
