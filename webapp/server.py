"""The HTTP server for the webapp: Werkzeug's threaded WSGI server in a background thread.

Flask-SocketIO's threading mode runs on it (WebSocket through simple-websocket); that is enough
for a handful of Robot Editor browsers on a robot. We bind first and serve in a thread (rather
than socketio.run(), which blocks and cannot be stopped from outside) so that `serve` can stop it
in order with the daemon and the worker, and so port 0 (tests) reports the port it got.
"""
from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)


class ServerError(RuntimeError):
    """The server cannot start (the port is taken, the address is not local); the message says which."""


class HttpServer:
    def __init__(self, app, host: str, port: int):
        import socket

        from werkzeug.serving import make_server, select_address_family

        # Werkzeug logs every request at INFO; keep the service logs about the service.
        logging.getLogger("werkzeug").setLevel(logging.WARNING)
        # Bind here (werkzeug would print its own message and sys.exit on a taken port).
        family = select_address_family(host, port)
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(128)
            bound_port = sock.getsockname()[1]
            self._server = make_server(host, bound_port, app, threaded=True, fd=sock.fileno())
        except OSError as exc:
            raise ServerError(f"cannot listen on {host}:{port}: {exc.strerror or exc} "
                              "(set another port with --port or HOPE_PORT)") from None
        finally:
            sock.close()  # the server holds its own duplicate of the descriptor
        self.host = host
        self.port = bound_port
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = self.host
        if host in ("0.0.0.0", "::", ""):
            host = "127.0.0.1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/"

    def start(self) -> None:
        self._thread = threading.Thread(target=self._server.serve_forever, name="http", daemon=True)
        self._thread.start()
        log.info("webapp listening on %s", self.url)

    def stop(self, timeout: float = 5.0) -> None:
        self._server.shutdown()
        self._server.server_close()
        if self._thread is not None:
            self._thread.join(timeout)
