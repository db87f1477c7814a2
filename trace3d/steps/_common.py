"""Helpers of the step handlers."""

from __future__ import annotations

import json

from ..errors import Trace3DError


def json_arg(text: str | None, flag: str) -> dict:
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise Trace3DError(f"{flag}: not valid JSON ({exc}).") from exc
    if not isinstance(value, dict):
        raise Trace3DError(f"{flag}: expected a JSON mapping, got {type(value).__name__}.")
    return value
