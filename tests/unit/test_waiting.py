"""roslab.reporting.waiting: a wait on many hosts names the slow ones every few seconds, never silent."""

from __future__ import annotations

import io

import gevent

from roslab.reporting import waiting


def test_a_wait_names_the_hosts_still_at_it_every_interval_and_is_quiet_when_all_are_quick():
    quick, slow = gevent.spawn(gevent.sleep, 0.01), gevent.spawn(gevent.sleep, 0.35)
    said = io.StringIO()
    waiting.joined({quick: "team1-main", slow: "team2-main"}, "roslab verify: still checking", every=0.1, out=said)
    assert slow.ready()
    lines = said.getvalue().splitlines()
    assert 2 <= len(lines) <= 4, lines  # every 0.1 s of the 0.35 s
    assert all(line.startswith("roslab verify: still checking team2-main (") for line in lines), lines
    said = io.StringIO()
    waiting.joined({gevent.spawn(gevent.sleep, 0.01): "team1-main"}, "x", every=0.5, out=said)
    assert said.getvalue() == ""


def test_a_wait_ends_at_its_timeout_leaving_the_slow_ones_running_and_says_nothing_past_it():
    stuck = gevent.spawn(gevent.sleep, 30)
    said = io.StringIO()
    waiting.joined({stuck: "robot"}, "still", timeout=0.25, every=0.1, out=said)
    assert not stuck.ready()
    stuck.kill()
    assert 1 <= len(said.getvalue().splitlines()) <= 2
