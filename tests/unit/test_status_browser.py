"""`roslab status`'s page in a real browser (Debian's chromium, headless): what a teacher sees.

The page is rendered from fixtures (a reachable, an unreachable and a never-run host, and
markup where names belong), opened from a file as a teacher would, and checked on the DOM
the browser built: each team and host with its state, the injected `<script>` as inert
text. A screenshot shows the browser painted it (not a blank page).
"""

from __future__ import annotations

import re

import pytest
from fixtures.browser import chromium, chromium_missing, distinct_rows, dump_dom, screenshot
from fixtures.status_hosts import HOSTILE, NOW, hostile_page, never_run_host, reachable_host, unreachable_host

from roslab.cli.status import page_context, render_page

pytestmark = pytest.mark.skipif(chromium_missing() is not None, reason=str(chromium_missing()))


def test_the_browser_shows_every_team_host_and_state(tmp_path):
    hosts = [reachable_host(), reachable_host(name="team1-robot", role="robot"), unreachable_host(name="team1-robot2"),
             never_run_host()]
    page = tmp_path / "status.html"
    page.write_text(render_page(page_context("robotics-lab", "classroom.yaml", hosts, NOW)))

    dom = dump_dom(page)

    assert re.findall(r'<section class="team" data-team="([^"]*)"', dom) == ["team1", "team2"]
    boxes = dict(re.findall(r'<g class="host" data-host="([^"]*)" data-level="([^"]*)"', dom))
    assert boxes == {"team1-main": "ok", "team1-robot": "ok", "team1-robot2": "bad", "team2-main": "warn"}
    rows = re.findall(r'<tr data-host="([^"]*)">(.*?)</tr>', dom, re.S)
    cells = {host: re.findall(r"<td[^>]*>(.*?)</td>", row, re.S) for host, row in rows}
    assert list(cells) == ["team1-main", "team1-robot", "team1-robot2", "team2-main"]
    assert cells["team1-main"][4:10] == ["ok", "24.04 noble", "jazzy", "11", "-", "active (running)"]
    assert cells["team1-robot2"][4] == "unreachable"
    assert cells["team2-main"][9:13] == ["not installed", "-", "never", "never"]
    assert dom.count('class="arrow unknown"') == 2  # two robots -> main, not listened


def test_markup_in_names_is_inert_text_in_the_browser(tmp_path):
    page = tmp_path / "status.html"
    page.write_text(hostile_page(listen=True))

    dom = dump_dom(page)

    as_text = HOSTILE.replace("<", "&lt;").replace(">", "&gt;")
    assert "<script" not in dom and "<img" not in dom  # no element came from a value
    # Had the script run, the title would be "pwned".
    assert re.search(r"<title>(.*?)</title>", dom).group(1) == f"roslab status: {as_text}"
    assert re.search(r"<h1>(.*?)</h1>", dom).group(1) == as_text  # shown, as text
    assert '<section class="team" data-team="&lt;script&gt;' in dom


def test_the_browser_paints_the_page(tmp_path):
    page = tmp_path / "status.html"
    page.write_text(hostile_page())
    blank = tmp_path / "blank.html"
    blank.write_text("<!DOCTYPE html><html><body></body></html>")

    shot = screenshot(page, tmp_path / "status.png")
    empty = screenshot(blank, tmp_path / "blank.png")

    assert distinct_rows(empty) <= 2  # the measure tells a blank page
    assert distinct_rows(shot) > 100


def test_after_a_failed_run_the_browser_shows_the_host_and_the_chip_red(tmp_path):
    from datetime import timedelta

    from roslab.reporting.runs import RunRecord

    failed = reachable_host(run=RunRecord(NOW - timedelta(minutes=2), "failed", "Ensure ROS 2 jazzy",
                                          "E: Unable to locate package x", NOW - timedelta(days=1)))
    hosts = [failed, reachable_host(name="team1-robot", role="robot")]
    page = tmp_path / "status.html"
    page.write_text(render_page(page_context("robotics-lab", "classroom.yaml", hosts, NOW)))

    dom = dump_dom(page)

    boxes = dict(re.findall(r'<g class="host" data-host="([^"]*)" data-level="([^"]*)"', dom))
    assert boxes == {"team1-main": "bad", "team1-robot": "ok"}
    chips = dict((text, level) for level, text in re.findall(r'<span class="(\w+)">([^<]*)</span>', dom))
    assert chips["1 failed in their last run"] == "bad"
    assert chips["2 reachable"] == "ok"
    row = re.search(r'<tr data-host="team1-main">(.*?)</tr>', dom, re.S).group(1)
    assert '<td class="bad">failed ' in row


def page_width(page, window_width: int) -> tuple[int, int]:
    """(the page's full width, the host table's) as the browser laid them out in a window
    `window_width` wide. The page forbids scripts (its CSP): a copy without that line carries
    the test's own measuring script."""
    measured = page.with_name("measured.html")
    html = re.sub(r'<meta http-equiv="Content-Security-Policy"[^>]*>', "", page.read_text())
    measured.write_text(html.replace("</body>", (
        "<script>document.body.dataset.page = document.documentElement.scrollWidth;"
        "document.body.dataset.table = Math.ceil(document.querySelector('table').getBoundingClientRect().right);"
        "</script></body>")))
    dom = chromium(measured, f"--window-size={window_width},900", "--dump-dom").stdout
    body = re.search(r'<body data-page="(\d+)" data-table="(\d+)">', dom)
    assert body, dom[:500]
    return int(body[1]), int(body[2])


def test_a_four_robot_class_fits_a_1280_pixel_window_with_nothing_cut(tmp_path):
    # The teacher's day-three class: an ESP32 team whose main runs no nodes service, a rover
    # team whose robot is unreachable with a long error, a TurtleBot 4 team, a sim team.
    hosts = [reachable_host(name="knob-main", team="knob", profile="esp32_microros", runs_nodes=False),
             reachable_host(name="knob-robot", role="robot", team="knob", profile="esp32_microros"),
             reachable_host(name="rover-main", team="rover", profile="osr"),
             unreachable_host(name="rover-robot", team="rover"),
             reachable_host(name="tb4-main", team="tb4", profile="turtlebot4"),
             reachable_host(name="tb4-robot", role="robot", team="tb4", profile="turtlebot4"),
             never_run_host(name="sim-main")]
    hosts[3].error = "Could not connect ([Errno 113] No route to host) while reading the host's facts " * 3
    page = tmp_path / "status.html"
    page.write_text(render_page(page_context("robotics-lab", "classroom.yaml", hosts, NOW)))

    full, table = page_width(page, 1280)

    assert full <= 1280 and table <= 1280, (full, table)  # no column, NOTE least of all, past the edge
    dom = dump_dom(page)
    knob_main = re.search(r'<g class="host" data-host="knob-main".*?</g>', dom, re.S)[0]
    box = re.search(r'<rect class="box ok" x="\d+" y="(\d+)" width="\d+" height="(\d+)"', knob_main)
    lines = [(int(y), text) for y, text in re.findall(r'<text class="[^"]*" x="\d+" y="(\d+)">([^<]*)</text>',
                                                       knob_main)]
    assert "nodes: none (esp32_microros main)" in " ".join(text for _, text in lines)  # wrapped, not cut
    assert "\u2026" not in knob_main
    assert all(y < int(box[1]) + int(box[2]) for y, _ in lines)  # every line inside its box
