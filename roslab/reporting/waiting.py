"""A wait on many hosts at once that is never silent (issue 40: no silent stretch over 20 s).

`roslab verify` and `roslab status` check every host in parallel (gevent greenlets, as pyinfra
connects); a check can take longer than its listening bound (SSH, the ROS tools' own start on a
loaded Pi). While any host is still at it, one line every `EVERY` seconds names those hosts and
how long the wait has lasted, so the teacher sees which one is slow.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

EVERY = 10.0  # seconds between "still ..." lines: well inside the 20 s a teacher waits in silence


def joined(jobs: dict, saying: str, timeout: float | None = None, every: float = EVERY,
           out: TextIO | None = None, clock=time.monotonic) -> None:
    """Wait for every greenlet of `jobs` (greenlet -> host name), at most `timeout` seconds (None:
    until all are done). Every `every` seconds while some are not done, one line to `out`
    (stderr): `{saying} NAME, NAME (12 s)`, the names sorted. Nothing is said when all are done
    within `every` seconds."""
    import gevent

    out = out if out is not None else sys.stderr
    started = clock()
    pending = dict(jobs)
    while pending:
        left = None if timeout is None else timeout - (clock() - started)
        if left is not None and left <= 0:
            return
        gevent.joinall(list(pending), timeout=every if left is None else min(every, left))
        pending = {job: name for job, name in pending.items() if not job.ready()}
        if pending and (timeout is None or clock() - started < timeout):
            names = ", ".join(sorted(set(pending.values())))
            print(f"{saying} {names} ({clock() - started:.0f} s)", file=out, flush=True)
