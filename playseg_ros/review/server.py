"""The review page's HTTP server (the standard library's threading server: nothing to install).

Routes (JSON unless said otherwise; with a token, every /api route needs ``?token=``; the page and its
static files, which hold no data, do not). A server without a token (bound to localhost) answers only
requests addressed to this machine's names, and takes writes only as JSON from its own origin, so a page of
another site open in the same browser can neither read nor write through it:

    GET  /                                  the page (static/index.html)
    GET  /static/<file>                     the page's script and style
    GET  /api/info                          dataset, vocabulary, episodes in queue order, model, jobs
    GET  /api/episode/<i>                   an episode's labels, proposals, version, cameras, signals
    GET  /api/episode/<i>/signals?start=&end=&points=   plotted channels over a window of observations
    GET  /api/episode/<i>/video/<camera>?chunk=<c>   MP4 of the episode's c-th chunk of observations
                                            (video.py; encoded once, cached), with HTTP range requests
    POST /api/episode/<i>/save              {labels, version, reviewed, rejected} -> {version} or 409
    POST /api/propose | /api/retrain        start a background job; GET /api/jobs polls them
    GET  /api/export/preview                the language_persistent rows an export would write
    POST /api/export                        {out}: the reviewed dataset as LeRobot v3.0
    POST /api/export/mcap                   {out}: the labels as an MCAP for Foxglove (foxglove.py)
"""

from __future__ import annotations

import hmac
import json
import mimetypes
import re
import socket
import traceback
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

from playseg_core.errors import PlaysegError
from playseg_ros.review.session import ReviewSession
from playseg_ros.review.store import VersionConflict
from playseg_ros.review.video import episode_video, prefetch_chunk

STATIC = Path(__file__).with_name("static")
LOCAL_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})
"""Host names of this machine that a page served on localhost is opened at."""
MAX_BODY = 8 * 1024 * 1024
CHUNK = 1 << 16


class ReviewServer(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(
        self, address: tuple[str, int], session: ReviewSession, token: str | None, actions: Any
    ) -> None:
        if ":" in address[0]:  # an IPv6 address
            self.address_family = socket.AF_INET6
        super().__init__(address, ReviewHandler)
        self.session, self.token, self.actions = session, token, actions


class ReviewHandler(BaseHTTPRequestHandler):
    server: ReviewServer
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the base class's name)
        pass  # one line per request would drown the URL the user needs

    # ----------------------------------------------------------------------------------------------

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        self._handle("GET")

    def do_HEAD(self) -> None:  # noqa: N802
        self._handle("HEAD")

    def do_POST(self) -> None:  # noqa: N802
        self._handle("POST")

    def _handle(self, method: str) -> None:
        url = urlsplit(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        token = self.server.token
        public = url.path in ("/", "/index.html") or url.path.startswith("/static/")  # the page's own code
        given = query.get("token", self.headers.get("X-Review-Token", ""))
        if token and not public and not hmac.compare_digest(given.encode(), token.encode()):
            self._json(
                {"error": "a token is needed: open the URL `playseg review` printed"}, HTTPStatus.FORBIDDEN
            )
            return
        if not token and (refused := self._foreign_request(method)):
            self._json({"error": refused}, HTTPStatus.FORBIDDEN)
            return
        try:
            self._route(method, unquote(url.path), query)
        except VersionConflict as error:
            self._json({"error": str(error)}, HTTPStatus.CONFLICT)
        except (PlaysegError, OSError, KeyError, ValueError, TypeError) as error:  # bad input, one line
            self._json({"error": " ".join(str(error).split())}, HTTPStatus.BAD_REQUEST)
        except Exception as error:  # a bug: the page gets one line, the console the traceback
            traceback.print_exc()
            self._json({"error": f"internal error: {type(error).__name__}"}, HTTPStatus.INTERNAL_SERVER_ERROR)

    def _foreign_request(self, method: str) -> str | None:
        """Without a token (a localhost server), what another site's page could send: a request whose Host
        is not this machine (DNS rebinding), or a write that is not the page's JSON from this origin (a
        cross-site form or `text/plain` fetch needs no preflight). The reason to refuse it, or None."""
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0].strip("[]")
        if host not in LOCAL_NAMES:
            return f"host {host!r} refused: open the page at http://127.0.0.1 (or bind with a token)"
        if method == "POST":
            if (self.headers.get("Content-Type") or "").split(";")[0].strip() != "application/json":
                return "a write must be application/json"
            origin = self.headers.get("Origin")
            if origin is not None and (urlsplit(origin).hostname or "") not in LOCAL_NAMES:
                return f"origin {origin!r} refused"
        return None

    def _route(self, method: str, path: str, query: dict[str, str]) -> None:
        session = self.server.session
        if method in ("GET", "HEAD"):
            if path in ("/", "/index.html"):
                self._file(STATIC / "index.html")
            elif path.startswith("/static/") and re.fullmatch(r"/static/[\w.-]+", path):
                self._file(STATIC / path.removeprefix("/static/"))
            elif path == "/api/info":
                self._json(self.server.actions.info())
            elif path == "/api/jobs":
                self._json({name: job.to_json() for name, job in session.jobs.items()})
            elif path == "/api/export/preview":
                self._json(self.server.actions.export_preview())
            elif match := re.fullmatch(r"/api/episode/(\d+)", path):
                self._json(session.episode(int(match[1])))
            elif match := re.fullmatch(r"/api/episode/(\d+)/signals", path):
                start, end = int(query.get("start", 0)), int(query.get("end", 1 << 62))
                self._json(session.signals(int(match[1]), start, end, int(query.get("points", 1000))))
            elif match := re.fullmatch(r"/api/episode/(\d+)/video/(.+)", path):
                index, camera = int(match[1]), match[2]
                session.check_index(index)
                if camera not in session.dataset.features.cameras:
                    raise PlaysegError(f"no camera {camera!r} in this dataset")
                chunk, frames = int(query.get("chunk", 0)), session.video_chunk
                video = episode_video(session.dataset, index, camera, session.cache_dir, chunk, frames)
                prefetch_chunk(session.dataset, index, camera, session.cache_dir, chunk + 1, frames)
                self._file(video, ranges=True)
            else:
                self._json({"error": f"no page {path}"}, HTTPStatus.NOT_FOUND)
            return
        body = self._body()
        if match := re.fullmatch(r"/api/episode/(\d+)/save", path):
            self._json(session.save(int(match[1]), body))
        elif path == "/api/propose":
            self._json(session.start_job("propose", session.propose).to_json())
        elif path == "/api/retrain":
            self._json(self.server.actions.retrain(body).to_json())
        elif path == "/api/export/mcap":
            self._json(self.server.actions.export_mcap(body))
        elif path == "/api/export":
            self._json(self.server.actions.export(body).to_json())
        else:
            self._json({"error": f"no action {path}"}, HTTPStatus.NOT_FOUND)

    # ----------------------------------------------------------------------------------------------

    def _body(self) -> dict[str, Any]:
        length = int(self.headers.get("Content-Length") or 0)
        if length > MAX_BODY:
            raise PlaysegError(f"request body of {length} bytes is over {MAX_BODY}")
        try:
            body = json.loads(self.rfile.read(length) or b"{}")
        except ValueError as error:
            raise PlaysegError(f"request body is not JSON ({error})") from None
        if not isinstance(body, dict):
            raise PlaysegError("request body must be a JSON object")
        return body

    def _json(self, value: Any, status: HTTPStatus = HTTPStatus.OK) -> None:
        data = json.dumps(value, allow_nan=False, default=str).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(data)

    def _file(self, path: Path, ranges: bool = False) -> None:
        """A file; with ``ranges`` a ``Range: bytes=a-b`` request gets 206 and that part (video seeking)."""
        if not path.is_file():
            self._json({"error": f"no file {path.name}"}, HTTPStatus.NOT_FOUND)
            return
        size = path.stat().st_size
        start, end, status = 0, size - 1, HTTPStatus.OK
        header = self.headers.get("Range", "")
        if ranges and (match := re.fullmatch(r"bytes=(\d*)-(\d*)", header.strip())):
            first, last = match[1], match[2]
            if first:
                start, end = int(first), min(int(last), size - 1) if last else size - 1
            elif last:
                start = max(0, size - int(last))
            if start > end or start >= size:
                self.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                self.send_header("Content-Range", f"bytes */{size}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            status = HTTPStatus.PARTIAL_CONTENT
        self.send_response(status)
        kind = "video/mp4" if path.suffix == ".mp4" else mimetypes.guess_type(path.name)[0] or "text/plain"
        self.send_header(
            "Content-Type",
            kind + ("; charset=utf-8" if kind.startswith(("text/", "application/javascript")) else ""),
        )
        self.send_header("Content-Length", str(end - start + 1))
        if ranges:
            self.send_header("Accept-Ranges", "bytes")
        if status == HTTPStatus.PARTIAL_CONTENT:
            self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        if self.command == "HEAD":
            return
        with open(path, "rb") as handle:
            handle.seek(start)
            left = end - start + 1
            while left > 0:
                chunk = handle.read(min(CHUNK, left))
                if not chunk:
                    break
                self.wfile.write(chunk)
                left -= len(chunk)
