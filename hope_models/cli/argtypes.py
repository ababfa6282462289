"""argparse `type=` checkers shared by every sub-command, so a bad value gets the same one-line
message (naming the value and the rule) from `train`, `enqueue`, `sim-demos` or `daemon` alike.
Numbers are read by the one rule of hope_models/numbers.py (a JSON number's text;
an integer as decimal digits). Torch-free and cheap: parsers import this
module before any command runs. TrainConfig's own flags get theirs from train/config.py."""
from __future__ import annotations

import argparse
from typing import Any, Callable

from hope_models.numbers import NumberError, float_from_text, int_from_text


def _number(parse: Callable[..., Any], text: str, **bounds: Any) -> Any:
    try:
        return parse("value", text, **bounds)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason) from None


def non_negative_int(text: str) -> int:
    return _number(int_from_text, text, minimum=0)


def positive_int(text: str) -> int:
    return _number(int_from_text, text, minimum=1)


def positive_float(text: str) -> float:
    return _number(float_from_text, text, above=0.0)


def non_negative_float(text: str) -> float:
    return _number(float_from_text, text, minimum=0.0)
