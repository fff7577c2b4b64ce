"""The last deploy.py run on each host, kept on the controller beside the roster.

    <roster dir>/.roslab-state/runs.yaml

`roslab.reporting.summary` records every host of a real run (not a --dry one) when the run ends:
when it ran, how it ended (`ok`, `changed`, `failed` with the step and one line of why,
`not run` when the run stopped before it), and when it last ended well (`ok` or
`changed`). `roslab status` reads it. Nothing is written onto the hosts: a timestamp
there would make every run a change.

    team1-main:
      last_run: '2026-11-23T08:31:02Z'
      result: changed
      last_success: '2026-11-23T08:31:02Z'

The file is rewritten atomically (a temporary file renamed over it) under a lock, so two
runs that end at once (`--limit team1` and `--limit team2`) both land.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable

import yaml

from roslab.controller_files import file_lock, replace_file
from roslab.network.state import STATE_DIR

RUNS_FILE = "runs.yaml"
HEADER = ("# managed by roslab (roslab/reporting/runs.py): the last deploy.py run per host, "
          "written at the end of each run.\n")
# Results that count as a successful run.
SUCCESS_RESULTS = ("ok", "changed")
MAX_TEXT = 240  # characters kept of a step or reason


def runs_path(roster_path: str | os.PathLike) -> Path:
    return Path(roster_path).resolve().parent / STATE_DIR / RUNS_FILE


def now_utc() -> datetime:
    return datetime.now(timezone.utc).replace(microsecond=0)


def format_time(moment: datetime) -> str:
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_time(text: object) -> datetime | None:
    """A recorded time, or None if it is missing or not a time."""
    if isinstance(text, datetime):  # YAML may read an unquoted timestamp itself
        return text if text.tzinfo else text.replace(tzinfo=timezone.utc)
    if not isinstance(text, str):
        return None
    try:
        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        return None
    return moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)


@dataclass(frozen=True)
class HostRun:
    """What one run did to one host."""

    host: str
    result: str  # ok, changed, failed, not run
    step: str | None = None
    reason: str | None = None


@dataclass(frozen=True)
class RunRecord:
    """A host's entry in runs.yaml, as `roslab status` reads it."""

    last_run: datetime | None = None
    result: str | None = None
    step: str | None = None
    reason: str | None = None
    last_success: datetime | None = None


def _text(value: object) -> str | None:
    if value is None:
        return None
    text = " ".join(str(value).split())
    return text[:MAX_TEXT] if text else None


def _load(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except FileNotFoundError:
        return {}
    if not isinstance(data, dict):
        raise ValueError("not a mapping of host name to its last run")
    return {str(name): entry for name, entry in data.items() if isinstance(entry, dict)}


def read_runs(roster_path: str | os.PathLike) -> dict[str, RunRecord]:
    """Every host's recorded run. Raises OSError, ValueError or yaml.YAMLError on a broken file."""
    records = {}
    for name, entry in _load(runs_path(roster_path)).items():
        records[name] = RunRecord(
            last_run=parse_time(entry.get("last_run")),
            result=_text(entry.get("result")),
            step=_text(entry.get("step")),
            reason=_text(entry.get("reason")),
            last_success=parse_time(entry.get("last_success")),
        )
    return records


def _locked(path: Path):
    return file_lock(path.parent / f".{path.name}.lock")


def record_runs(roster_path: str | os.PathLike, runs: Iterable[HostRun], when: datetime | None = None) -> Path:
    """Record one run's outcome per host (other hosts' entries are kept as they were)."""
    when = when or now_utc()
    stamp = format_time(when)
    path = runs_path(roster_path)
    with _locked(path):
        try:
            entries = _load(path)
        except (ValueError, yaml.YAMLError):
            entries = {}  # a broken file is replaced by this run's record rather than kept broken
        for run in runs:
            entry: dict[str, str | None] = {"last_run": stamp, "result": run.result}
            if run.step:
                entry["step"] = _text(run.step)
            if run.reason:
                entry["reason"] = _text(run.reason)
            previous = entries.get(run.host) or {}
            if run.result in SUCCESS_RESULTS:
                entry["last_success"] = stamp
            elif (last_success := parse_time(previous.get("last_success"))) is not None:
                entry["last_success"] = format_time(last_success)
            entries[run.host] = entry
        replace_file(path, HEADER + yaml.safe_dump(dict(sorted(entries.items())), default_flow_style=False,
                                                   sort_keys=False, allow_unicode=True), mode=0o600)
    return path
