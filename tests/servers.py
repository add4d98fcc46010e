"""HTTP servers on 127.0.0.1 for the download tests (the tests reach no other address)."""

from __future__ import annotations

import contextlib
import http.server
import threading
from collections.abc import Iterator
from typing import Any

PROXY_VARIABLES = ("http_proxy", "https_proxy", "all_proxy", "HTTP_PROXY", "HTTPS_PROXY",
                   "ALL_PROXY")  # fmt: skip


def direct(monkeypatch) -> None:
    """No proxy from the environment: every request goes to 127.0.0.1 itself."""
    for k in PROXY_VARIABLES:
        monkeypatch.delenv(k, raising=False)


@contextlib.contextmanager
def serve(handler: Any, **attrs: Any) -> Iterator[http.server.ThreadingHTTPServer]:
    """A threading HTTP server of ``handler`` on a free port of 127.0.0.1, in a daemon thread,
    with ``attrs`` set on it before it starts (the handler reads them as ``self.server.NAME``)
    and its address as ``.url``; shut down and closed when the block ends."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    for name, value in attrs.items():
        setattr(srv, name, value)
    srv.url = f"http://127.0.0.1:{srv.server_address[1]}"
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        yield srv
    finally:
        srv.shutdown()
        srv.server_close()
