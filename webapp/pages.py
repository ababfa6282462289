"""The Robot Editor's pages: one HTML shell and our static JS/CSS (webapp/static/).

    GET /                        the editor (login, then Jobs, Run, Compare, Episodes, System, Workers, Models,
                                 Inference via #hash; #run/<id> opens one run)
    GET /jobs, /episodes, ...    the same shell (a bookmarked or reloaded page lands where it was)

The pages themselves are open: they hold no data. Everything they show comes from /api/ with the
bearer token the user typed at the login (kept in the browser's localStorage) and from Socket.IO
with the same token (webapp/auth.py refuses either without it).

The browser libraries (socket.io-client, chart.js, hammer.js, chartjs-plugin-zoom) are served from
webapp/static/vendor/, copied there from npm at setup time (webapp/build_assets.py): no CDN, a robot is often offline. When they
are missing the page says what to run instead of failing silently.

A strict Content-Security-Policy: scripts only from this server, connections only back to it.
"""
from __future__ import annotations

from flask import Blueprint, Response, render_template

from webapp.build_assets import VENDOR_FILES, missing_vendor_files

bp = Blueprint("pages", __name__)

PAGES = ("jobs", "run", "compare", "episodes", "system", "workers", "models", "inference")
# 'unsafe-inline' styles only: Chart.js sizes its canvas through style attributes.
CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
       "connect-src 'self' ws: wss:; frame-ancestors 'none'; base-uri 'none'; form-action 'self'")


def _shell(page: str) -> Response:
    html = render_template("editor.html", page=page, pages=PAGES, vendor=list(VENDOR_FILES),
                           missing_vendor=missing_vendor_files())
    response = Response(html, mimetype="text/html")
    response.headers["Content-Security-Policy"] = CSP
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = "no-referrer"
    # the shell is tiny; never cache it so an upgrade's new JS names are picked up at once
    response.headers["Cache-Control"] = "no-store"
    return response


@bp.get("/")
def index():
    return _shell("jobs")


@bp.get("/<any(jobs, run, compare, episodes, system, workers, models, inference):page>")
def page(page: str):
    return _shell(page)
