"""roslab.reporting.waiting: a wait on many hosts names the slow ones every few seconds, never silent."""

from __future__ import annotations

import io
import re

import gevent

from roslab.reporting import waiting


def test_a_wait_names_the_hosts_still_at_it_every_interval_and_is_quiet_when_all_are_quick():
    said = io.StringIO()
    quick = gevent.spawn(lambda: None)
    quick.join()  # done before the wait: never named

    def slow() -> None:  # done once two lines named it: the test does not race the clock
        while said.getvalue().count("\n") < 2:
            gevent.sleep(0.01)

    slow_job = gevent.spawn(slow)
    waiting.joined({quick: "team1-main", slow_job: "team2-main"}, "roslab verify: still checking", every=0.1,
                   out=said)
    assert slow_job.ready()
    lines = said.getvalue().splitlines()
    assert 2 <= len(lines) <= 3, lines
    assert all(re.fullmatch(r"roslab verify: still checking team2-main \(\d+ s\)", line) for line in lines), lines
    said = io.StringIO()
    waiting.joined({quick: "team1-main"}, "x", every=0.5, out=said)
    assert said.getvalue() == ""


def test_a_wait_ends_at_its_timeout_leaving_the_slow_ones_running_and_says_nothing_past_it():
    import time

    stuck = gevent.spawn(gevent.sleep, 30)
    said = io.StringIO()
    started = time.monotonic()
    waiting.joined({stuck: "robot"}, "still", timeout=0.25, every=0.1, out=said)
    assert 0.25 <= time.monotonic() - started < 10 and not stuck.ready()
    stuck.kill()
    lines = said.getvalue().splitlines()
    assert len(lines) <= 2 and all(re.fullmatch(r"still robot \(\d+ s\)", line) for line in lines), lines
