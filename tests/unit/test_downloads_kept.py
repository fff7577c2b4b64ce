"""rosdep's data kept on the controller: each run a conditional request (a 304 costs no
body), and upstream down uses the kept copy and says so (loopback server)."""

from __future__ import annotations

import os
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from roslab import downloads


class Upstream:
    def __init__(self):
        self.body, self.etag, self.requests = b"rules v1\n", '"v1"', []
        upstream = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):
                upstream.requests.append(dict(self.headers))
                if self.headers.get("If-None-Match") == upstream.etag:
                    self.send_response(304)
                    self.end_headers()
                    return
                self.send_response(200)
                self.send_header("ETag", upstream.etag)
                self.send_header("Content-Length", str(len(upstream.body)))
                self.end_headers()
                self.wfile.write(upstream.body)

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/rosdep/base.yaml"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def stop(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def upstream():
    server = Upstream()
    yield server
    server.stop()


def new_run():
    """What a new pyinfra run starts with: nothing fetched yet."""
    downloads._fetched.clear()
    downloads._fetched_validators.clear()
    downloads._kept_this_run.clear()


def age(cache, seconds):
    for path in cache.rglob("*"):
        if path.is_file():
            os.utime(path, (time.time() - seconds,) * 2)


def test_each_run_checks_the_kept_copy_with_a_conditional_request(upstream, tmp_path):
    new_run()
    assert downloads.kept(upstream.url, tmp_path, max_age=3600) == downloads.Kept(b"rules v1\n")
    new_run()
    assert downloads.kept(upstream.url, tmp_path, max_age=3600).data == b"rules v1\n"
    assert len(upstream.requests) == 2
    assert upstream.requests[-1]["If-None-Match"] == '"v1"'  # answered 304: no body
    # The same URL serving other content (a mirror updated, a sandbox rebuilt) within the
    # max age: the next run takes it, never the old copy.
    upstream.body, upstream.etag = b"rules v2\n", '"v2"'
    new_run()
    assert downloads.kept(upstream.url, tmp_path, max_age=3600).data == b"rules v2\n"


def test_after_the_max_age_a_conditional_request_confirms_or_replaces_the_copy(upstream, tmp_path):
    new_run()
    downloads.kept(upstream.url, tmp_path, max_age=3600)
    age(tmp_path, 7200)
    new_run()
    assert downloads.kept(upstream.url, tmp_path, max_age=3600) == downloads.Kept(b"rules v1\n")
    assert upstream.requests[-1]["If-None-Match"] == '"v1"'  # answered 304: no body
    upstream.body, upstream.etag = b"rules v2\n", '"v2"'
    age(tmp_path, 7200)
    new_run()
    assert downloads.kept(upstream.url, tmp_path, max_age=3600).data == b"rules v2\n"


def test_upstream_down_uses_the_kept_copy_and_says_so(upstream, tmp_path):
    new_run()
    downloads.kept(upstream.url, tmp_path, max_age=3600)
    upstream.stop()
    age(tmp_path, 3 * 86400)
    new_run()
    got = downloads.kept(upstream.url, tmp_path, max_age=3600)
    assert got.data == b"rules v1\n"
    assert got.stale.startswith(f"cannot download {upstream.url}: ")
    assert "using the controller's copy from 3 days ago" in got.stale and "\n" not in got.stale


def test_upstream_down_without_a_kept_copy_is_an_error_naming_the_url(upstream, tmp_path):
    upstream.stop()
    new_run()
    with pytest.raises(downloads.DownloadError, match=f"cannot download {upstream.url}"):
        downloads.kept(upstream.url, tmp_path, max_age=3600)


def test_a_url_kept_twice_in_one_run_is_asked_conditionally_the_next_run(upstream, tmp_path):
    """The package check (no max age) and rosdep's data (a max age) keep the same rosdistro
    index in one run; the second used to drop its validators, so every run downloaded it."""
    new_run()
    downloads.kept(upstream.url, tmp_path)
    downloads.kept(upstream.url, tmp_path, max_age=3600)
    new_run()
    downloads.kept(upstream.url, tmp_path)
    assert upstream.requests[-1]["If-None-Match"] == '"v1"'  # answered 304: no body
