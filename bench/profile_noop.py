"""Profile one pyinfra run on the controller's CPU time: where a no-op re-run spends it.

Runs pyinfra's CLI in this process under cProfile with `time.process_time` as its clock
(CPU, not wall: waiting on SSH costs nothing here, and other processes on a busy machine
do not count), and writes a JSON summary:

- `stages`: CPU seconds in each of pyinfra's stages (Setup: inventory and roster;
  Connect: SSH; Prepare: deploy.py once per host, facts; Execute: the operations;
  Disconnect: results), read from `State.set_stage` without the profiler's overhead
  being told apart (all stages carry it alike);
- `operation_order`: calls and CPU of pyinfra's `get_operation_order_from_stack` and of
  roslab's (roslab.pyinfra_planning), whichever ran;
- `by_package`: self CPU summed by top-level module (`pyinfra`, `inspect`, `paramiko`, ...);
- `top_self` / `top_cumulative`: the functions that cost most, on their own and with what
  they call (cumulative times are unreliable across gevent's greenlet switches; the
  operation-order functions never switch).

Usage (from the repository, with the sandbox's environment for inventories/sandbox.py):

    .venv/bin/python bench/profile_noop.py --out /tmp/noop.json [--pstats F] -- -y inventories/sandbox.py deploy.py

ROSLAB_PYINFRA_PLANNING=pyinfra in the environment profiles pyinfra's own operation order.
bench/noop_rerun.py runs this once per variant and keeps the summary in its results.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from collections import defaultdict
from pathlib import Path

OPERATION_ORDER = {
    "pyinfra": ("pyinfra/api/util.py", "get_operation_order_from_stack"),
    "roslab": ("roslab/pyinfra_planning.py", "get_operation_order_from_stack"),
}


def package_of(filename: str) -> str:
    """A profile entry's top-level module: 'pyinfra', 'inspect', 'paramiko', '~' (builtins)."""
    if filename == "~":
        return "builtins"
    path = Path(filename)
    parts = path.parts
    if "site-packages" in parts:
        return parts[parts.index("site-packages") + 1].removesuffix(".py")
    for top in ("roslab", "deploy", "pyinfra", "pyinfra_cli"):
        if top in parts:
            return top
    if path.name == "deploy.py":
        return "deploy"
    return path.stem.strip("<>")  # stdlib modules (inspect, linecache, posixpath, ...)


def label(key: tuple) -> str:
    filename, line, name = key
    parts = Path(filename).parts
    short = "/".join(parts[-2:]) if len(parts) > 1 else filename
    return f"{short}:{line}({name})"


def summarise(profile: cProfile.Profile, stages: dict[str, float], total: float, top: int) -> dict:
    stats = pstats.Stats(profile).stats  # key -> (primitive calls, calls, self, cumulative, callers)
    by_package: dict[str, float] = defaultdict(float)
    for (filename, _, _), (_, _, self_time, _, _) in stats.items():
        by_package[package_of(filename)] += self_time
    order = {}
    for variant, (suffix, name) in OPERATION_ORDER.items():
        for (filename, _, function), (_, calls, _, cumulative, _) in stats.items():
            if function == name and filename.endswith(suffix):
                order[variant] = {"calls": calls, "cpu_s": round(cumulative, 3),
                                  "share": round(cumulative / total, 3) if total else 0}
    ranked_self = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)[:top]
    ranked_cumulative = sorted(stats.items(), key=lambda item: item[1][3], reverse=True)[:top]
    return {
        "cpu_s": round(total, 3),
        "stages": {stage: round(seconds, 3) for stage, seconds in stages.items()},
        "operation_order": order,
        "by_package": {name: round(seconds, 3) for name, seconds in
                       sorted(by_package.items(), key=lambda item: item[1], reverse=True)[:top]},
        "top_self": [{"function": label(key), "calls": value[1], "self_s": round(value[2], 3)}
                     for key, value in ranked_self],
        "top_cumulative": [{"function": label(key), "calls": value[1], "cumulative_s": round(value[3], 3)}
                           for key, value in ranked_cumulative],
    }


def run_pyinfra(arguments: list[str]) -> tuple[int, cProfile.Profile, dict[str, float], float]:
    """pyinfra's CLI with these arguments, profiled: exit code, profile, CPU per stage, CPU in all."""
    from pyinfra.api.state import State
    from pyinfra_cli.main import main

    stages: dict[str, float] = {}
    current = ["Setup", time.process_time()]
    pyinfra_set_stage = State.set_stage

    def set_stage(state, stage):
        now = time.process_time()
        stages[current[0]] = stages.get(current[0], 0.0) + now - current[1]
        current[:] = [stage.name, now]
        return pyinfra_set_stage(state, stage)

    State.set_stage = set_stage
    sys.argv = ["pyinfra", *arguments]
    profile = cProfile.Profile(time.process_time)
    started = time.process_time()
    code = 0
    profile.enable()
    try:
        main()
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    finally:
        profile.disable()
        State.set_stage = pyinfra_set_stage
    ended = time.process_time()
    stages[current[0]] = stages.get(current[0], 0.0) + ended - current[1]
    return code, profile, stages, ended - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the JSON summary")
    parser.add_argument("--pstats", type=Path, help="also the raw profile, for pstats / snakeviz")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("pyinfra_arguments", nargs=argparse.REMAINDER,
                        help="after --: pyinfra's arguments, e.g. -y inventories/sandbox.py deploy.py")
    args = parser.parse_args()
    arguments = args.pyinfra_arguments[1:] if args.pyinfra_arguments[:1] == ["--"] else args.pyinfra_arguments
    code, profile, stages, total = run_pyinfra(arguments)
    summary = summarise(profile, stages, total, args.top)
    summary["exit_code"] = code
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    if args.pstats:
        profile.dump_stats(args.pstats)
    return code


if __name__ == "__main__":
    sys.exit(main())
