"""A loopback HTTP server for the real-viewer test: the page that renders Foxglove Studio's prebuilt
web app, the npm packages it loads, and a run's files, with byte ranges (Studio's remote-file source
reads an MCAP file by HTTP Range requests)."""

from __future__ import annotations

import mimetypes
import re
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

PAGE = Path(__file__).resolve().parent / "studio_page.html"
_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")
_CHUNK_BYTES = 1 << 20
mimetypes.add_type("application/wasm", ".wasm")
mimetypes.add_type("text/javascript", ".js")


def _resolve(mounts: dict[str, Path], url_path: str) -> Path | None:
    """The file a URL path names under one of the mounts (prefix -> directory), or None; no escape."""
    if url_path in ("/", "/index.html"):
        return PAGE
    for prefix, root in mounts.items():
        if url_path.startswith(prefix + "/"):
            candidate = (root / url_path[len(prefix) + 1 :]).resolve()
            if candidate.is_file() and candidate.is_relative_to(root.resolve()):
                return candidate
    return None


def _handler(mounts: dict[str, Path]) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args: object) -> None:
            """Quiet: the test asserts on the page, not on the access log."""

        def do_HEAD(self) -> None:
            self._serve(send_body=False)

        def do_GET(self) -> None:
            self._serve(send_body=True)

        def _serve(self, send_body: bool) -> None:
            path = _resolve(mounts, unquote(urlsplit(self.path).path))
            if path is None:
                self.send_error(HTTPStatus.NOT_FOUND)
                return
            size = path.stat().st_size
            start, end = 0, size - 1
            status = HTTPStatus.OK
            header = self.headers.get("Range")
            if header is not None:
                match = _RANGE.match(header.strip())
                if match is None or (not match.group(1) and not match.group(2)):
                    self.send_error(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                    return
                if match.group(1):
                    start = int(match.group(1))
                    end = min(int(match.group(2)), size - 1) if match.group(2) else size - 1
                else:  # a suffix range: the last N bytes
                    start = max(size - int(match.group(2)), 0)
                if start >= size or start > end:
                    self.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                    self.send_header("Content-Range", f"bytes */{size}")
                    self.end_headers()
                    return
                status = HTTPStatus.PARTIAL_CONTENT
            self.send_response(status)
            self.send_header("Content-Type", mimetypes.guess_type(path.name)[0] or "application/octet-stream")
            self.send_header("Content-Length", str(end - start + 1))
            self.send_header("Accept-Ranges", "bytes")
            self.send_header("Cache-Control", "no-store")
            if status == HTTPStatus.PARTIAL_CONTENT:
                self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
            self.end_headers()
            if not send_body:
                return
            with path.open("rb") as stream:
                stream.seek(start)
                remaining = end - start + 1
                while remaining > 0:
                    block = stream.read(min(_CHUNK_BYTES, remaining))
                    if not block:
                        break
                    self.wfile.write(block)
                    remaining -= len(block)

    return Handler


@contextmanager
def serving(mounts: dict[str, Path]) -> Iterator[str]:
    """Serve the page at / and each mount's directory under its prefix on 127.0.0.1 (a free port);
    yields the base URL."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), _handler(mounts))
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, name="studio-http", daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)
