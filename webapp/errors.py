"""JSON errors: {"error": message} with the HTTP status, never an HTML page.

Bad input is a 4xx naming the field (views raise ApiError); Werkzeug's own errors (404 unknown
route, 405, 413 body too large, 415) get a message that says what to do. An unexpected exception
is logged with its traceback and answered 500 {"error": ...}: the API contract says bad input never
gets a 500, so a 500 is a bug to fix.

The body size limit (app.config["MAX_CONTENT_LENGTH"]) is checked from the Content-Length header
before anything else runs, so a 20 MB upload is refused without reading it (or asking for the
token first); a chunked body without a length is cut at the limit while it is read. A view marked
`large_body` (webapp/uploads.py: episode uploads, the app's handoff) gets settings.upload_max_mb
instead, checked the same way and set as that request's own limit.
"""
from __future__ import annotations

import logging

from flask import Flask, current_app, jsonify, request
from werkzeug.exceptions import HTTPException, MethodNotAllowed, NotFound, RequestEntityTooLarge

log = logging.getLogger(__name__)


LARGE_BODY_ATTR = "hope_large_body"  # set on a view by webapp.uploads.large_body


class ApiError(Exception):
    """Raised by a view to answer `status` {"error": message}."""

    def __init__(self, message: str, status: int = 400, retry_after_s: int | None = None):
        super().__init__(message)
        self.message = message
        self.status = status
        self.retry_after_s = retry_after_s  # a Retry-After header, for "not now" answers (429, 503)


def error_response(message: str, status: int, **extra):
    response = jsonify({"error": message, **extra})
    response.status_code = status
    return response


def _too_large_message() -> str:
    limit = request.max_content_length
    size = request.content_length
    got = f"{size} bytes" if size is not None else "more"
    return f"request body too large: {got}; the limit is {limit} bytes"


def install(app: Flask) -> None:
    @app.before_request
    def _body_size_first():
        # Before the token check and before any view reads the body.
        limit = app.config.get("MAX_CONTENT_LENGTH")
        view = app.view_functions.get(request.endpoint) if request.endpoint else None
        if view is not None and getattr(view, LARGE_BODY_ATTR, False):
            limit = int(current_app.extensions["hope"].settings.upload_max_mb) << 20
            request.max_content_length = limit  # a chunked body is cut here too, while it is read
        if limit is not None and request.content_length is not None and request.content_length > limit:
            return error_response(_too_large_message(), 413)
        return None

    @app.errorhandler(ApiError)
    def _api_error(exc: ApiError):
        response = error_response(exc.message, exc.status)
        if exc.retry_after_s is not None:
            response.headers["Retry-After"] = str(int(exc.retry_after_s))
        return response

    @app.errorhandler(HTTPException)
    def _http_error(exc: HTTPException):
        if isinstance(exc, RequestEntityTooLarge):
            return error_response(_too_large_message(), 413)
        if isinstance(exc, NotFound):
            return error_response(f"no such endpoint: {request.method} {request.path}", 404)
        if isinstance(exc, MethodNotAllowed):
            allowed = ", ".join(sorted(m for m in (exc.valid_methods or []) if m not in ("HEAD", "OPTIONS")))
            return error_response(f"{request.method} is not allowed on {request.path} (allowed: {allowed})", 405)
        response = error_response(exc.description or exc.name, exc.code or 500)
        return response

    @app.errorhandler(Exception)
    def _unexpected(exc: Exception):
        if isinstance(exc, HTTPException):
            return _http_error(exc)
        log.exception("unhandled error on %s %s", request.method, request.path)
        return error_response(f"internal error ({type(exc).__name__}); see the webapp log", 500)
