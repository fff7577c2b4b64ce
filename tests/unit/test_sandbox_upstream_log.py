"""The sandbox upstream logs every request (path, status, bytes) for tests to count fetches."""

from __future__ import annotations

import http.client
import socket
import time

from roslab.sandbox import upstream


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_every_request_is_logged_with_its_status_and_bytes_on_one_kept_alive_connection(tmp_path):
    served = tmp_path / "served"
    (served / "pool").mkdir(parents=True)
    (served / "pool/a_1.0_all.deb").write_bytes(b"x" * 1000)
    port = free_port()
    log = tmp_path / "upstream.log"
    upstream.start_server(served, "127.0.0.1", port, tmp_path / "upstream.pid", log)  # loopback only
    try:
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        for path in ("/pool/a_1.0_all.deb", "/pool/missing.deb", "/pool/a_1.0_all.deb"):
            connection.request("GET", path)
            response = connection.getresponse()
            response.read()  # HTTP/1.1: the next request goes on the same connection
        connection.close()
        # The server writes a request's line once its answer is sent, so the client can
        # have the last answer a moment before its line is written: wait for it (bounded)
        # rather than stop the server under it.
        deadline = time.monotonic() + 10
        while len(upstream.read_requests(tmp_path / upstream.REQUEST_LOG)) < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        upstream.stop_server(tmp_path / "upstream.pid")
    requests = upstream.read_requests(tmp_path / upstream.REQUEST_LOG)
    assert [(r.client, r.method, r.path, r.status, r.bytes) for r in requests] == [
        ("127.0.0.1", "GET", "/pool/a_1.0_all.deb", 200, 1000),
        ("127.0.0.1", "GET", "/pool/missing.deb", 404, 0),
        ("127.0.0.1", "GET", "/pool/a_1.0_all.deb", 200, 1000),
    ]
    assert not (tmp_path / "upstream.pid").exists()
