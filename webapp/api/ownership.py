"""GET /api/ownership/status: the Continuon app's robot list asks it before /api/ping.

    GET /api/ownership/status
        -> 200 {"status": "ok", "owned": bool, "subscription_active": false, "seed_installed": bool | null,
                "owner_id": null, "account_id": null, "account_type": null,
                "ownership": {the same six keys}, "token": "valid" | "missing" | "invalid",
                "name": "HOPE Seed Trainer", "device_id": "hope-<16 hex>",
                "seed_models": {component: version | null} (with the token only)}

What the app does with it (continuonai/lib/services/brain_client.dart fetchOwnershipStatus, read by
robot_list_screen.dart _refreshStatus and robot_init_state.dart RobotOwnershipStatus.fromJson): a
200 whose body is a JSON object, with a nested `ownership` object merged over it, is the status; any
other answer (an error status, a body that is not an object) becomes {} and the robot's card says
"Status fetch failed". It reads `owned`, `subscription_active`, `seed_installed` (`== true`, or
`as bool?`), and `owner_id`, `account_id`, `account_type` (`as String?`); an `account_id` that is
not null and differs from the signed-in account is shown as "Account mismatch". The answer carries
the nested object and the same keys at the top (the shape the Dart comment names for new servers),
so an app from before the merge reads it too.

Every value is a true statement about this trainer:
- owned: whether this request carries this trainer's bearer token. The trainer has no owner
  accounts: whoever holds $HOPE_HOME/token controls it, so that is what owning it means here.
- subscription_active: false. Nothing here is sold or subscribed to; the trainer needs no
  subscription for anything (the app asks for one only before its remote-control screen, which
  talks to a robot runtime on port 50051, not to the trainer).
- seed_installed: whether a promoted model is served (registry.promotion.promoted: any component
  has one); `seed_models` names the served version per component.
- owner_id, account_id, account_type: null. No account is configured on a trainer (no setting
  holds one), and null is what the app reads as "no account to compare" (never a mismatch).

No token needed, as for /api/ping (webapp/api/health.py), and for the same reason: the app calls
it without one when the user has set none (BrainClient._headers() adds `authorization` only when a
token is set), and it is read-only. Without the token it says no more than /api/ping does (name and
device_id, reused from there) plus owned: false and the constants above; `seed_installed` is then
null (not told) and `seed_models` absent. With a token that is not this trainer's it answers the
same way (token: "invalid"), rather than 401, so the robot list shows the trainer reachable and
not owned; the token's check is auth.py's constant-time one.
"""
from __future__ import annotations

from typing import Any

from flask import Blueprint, Response, current_app, jsonify

from hope_models.components import COMPONENTS
from registry import promotion
from webapp.api.health import NAME, device_id
from webapp.api.validation import query_args
from webapp.auth import bearer_token, public, tokens_match

bp = Blueprint("ownership", __name__, url_prefix="/api/ownership")


def _served(registry: Any) -> dict[str, str | None]:
    with registry.session(readonly=True) as s:
        out = {}
        for component in COMPONENTS:
            model = promotion.promoted(s, component)
            out[component] = model.version if model is not None else None
        return out


@bp.get("/status")
@public
def ownership_status() -> Response:
    query_args()
    hope = current_app.extensions["hope"]
    given = bearer_token()
    owned = tokens_match(given, hope.token)
    served = _served(hope.registry) if owned else None
    ownership: dict[str, Any] = {
        "owned": owned,
        "subscription_active": False,
        "seed_installed": None if served is None else any(v is not None for v in served.values()),
        "owner_id": None,
        "account_id": None,
        "account_type": None,
    }
    out: dict[str, Any] = {"status": "ok", **ownership, "ownership": dict(ownership),
                           "token": "valid" if owned else ("missing" if given is None else "invalid"),
                           "name": NAME, "device_id": device_id(str(hope.settings.home))}
    if served is not None:
        out["seed_models"] = served
    return jsonify(out)
