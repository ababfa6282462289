"""The app's JSON provider: every answer is valid JSON, whatever a view puts in it.

Python's json writes NaN and Infinity as bare words, which JSON does not have: browsers'
JSON.parse and the robot clients' strict parsers refuse the whole answer. A non-finite float is
turned into null (hope_models/json_finite.py, the rule of the registry and the promotion records),
also inside what `default` makes of other objects (dataclasses, dates), and allow_nan=False makes
any float that still slips through an error in the server's log rather than an answer no client
can read. Views that must not answer null where a number belongs check first (BrainService refuses
a non-finite action with a 500); this is the floor under every view. A lone UTF-16 surrogate (a
Dart string's, an undecodable file name's) is written as its `\\udXXX` escape whatever
ensure_ascii says (hope_models/rlds/json_text.py), so an answer is always valid UTF-8.
"""
from __future__ import annotations

from typing import Any

from flask.json.provider import DefaultJSONProvider

from hope_models.json_finite import finite
from hope_models.rlds.json_text import escape_surrogates


class FiniteJSONProvider(DefaultJSONProvider):
    def dumps(self, obj: Any, **kwargs: Any) -> str:
        default = kwargs.pop("default", self.default)
        kwargs["allow_nan"] = False
        return escape_surrogates(super().dumps(finite(obj), default=lambda o: finite(default(o)), **kwargs))


__all__ = ["FiniteJSONProvider"]
