"""A STAND-IN for an iRobot Create 3's web server (an emulation: no Create 3 exists here).

It answers only what deploy/robot_base.py sends, the way turtlebot4_setup sends it:

- GET `/api/about`: `{"version": "<firmware>", "emulation": "roslab Create 3 stand-in"}` (the
  real page's shape is not known here: the deploy only looks for a firmware version in it);
- POST `/ros-config-save-main` (form: ros_domain_id, ros_namespace, rmw_implementation),
  `/beta-ntp-conf-save` (form: config), `/api/reboot`: each recorded as one JSON line
  `{"path": ..., "form": {...}}` in the record file, so tests assert what a robot would have got;
- anything else: 404.

Run: `python -m roslab.sandbox.create3 --port 8080 --record posts.jsonl --firmware I.0.0.FastDDS`
(`--address` to listen elsewhere than 127.0.0.1). A request through an HTTP proxy (an absolute URL
on the request line, as curl sends with http_proxy) is answered by its path, so a test can send
the deploy's own commands, addressed to 192.168.186.2, to this stand-in on loopback.
"""

from __future__ import annotations

import argparse
import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

POST_PATHS = ("/ros-config-save-main", "/beta-ntp-conf-save", "/api/reboot")


def recorded_posts(record: Path) -> list[dict]:
    """What the stand-in was sent, in order: [{"path": ..., "form": {...}}]."""
    if not record.exists():
        return []
    return [json.loads(line) for line in record.read_text().splitlines() if line.strip()]


def handler_for(firmware: str, record: Path) -> type[BaseHTTPRequestHandler]:
    lock = threading.Lock()

    class Create3StandIn(BaseHTTPRequestHandler):
        server_version = "roslab-create3-standin"

        def answer(self, status: int, body: dict) -> None:
            data = json.dumps(body).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def do_GET(self):  # noqa: N802 (http.server's name)
            if urlsplit(self.path).path == "/api/about":
                self.answer(200, {"version": firmware, "emulation": "roslab Create 3 stand-in"})
            else:
                self.answer(404, {"error": "not emulated"})

        def do_POST(self):  # noqa: N802
            path = urlsplit(self.path).path
            body = self.rfile.read(int(self.headers.get("Content-Length") or 0)).decode("utf-8", "replace")
            if path not in POST_PATHS:
                self.answer(404, {"error": "not emulated"})
                return
            form = {key: values[-1] for key, values in parse_qs(body, keep_blank_values=True).items()}
            with lock, record.open("a") as stream:
                stream.write(json.dumps({"path": path, "form": form}, sort_keys=True) + "\n")
            self.answer(200, {"status": "saved" if path != "/api/reboot" else "rebooting"})

        def log_message(self, *args) -> None:  # quiet: the record says what happened
            return

    return Create3StandIn


def serve(address: str, port: int, firmware: str, record: Path) -> ThreadingHTTPServer:
    """A started stand-in (serving in a thread); `.shutdown()` stops it."""
    server = ThreadingHTTPServer((address, port), handler_for(firmware, record))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="roslab's stand-in for a Create 3's web server")
    parser.add_argument("--address", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=80)
    parser.add_argument("--firmware", default="I.0.0.FastDDS")
    parser.add_argument("--record", type=Path, required=True)
    options = parser.parse_args(argv)
    server = ThreadingHTTPServer((options.address, options.port), handler_for(options.firmware, options.record))
    server.serve_forever()


if __name__ == "__main__":
    main()
