"""Plain helpers shared by the service tests (imported as ``helpers``: pytest puts ``tests/`` on the path)."""

from __future__ import annotations

import json
import time
from typing import Any

FINAL = {"succeeded", "failed", "cancelled", "interrupted"}


def parse_sse(text: str) -> list[dict[str, Any]]:
    """Events of a ``text/event-stream`` body: dicts with ``id``, ``event`` and parsed ``data``."""
    events: list[dict[str, Any]] = []
    current: dict[str, Any] = {}
    for line in [*text.splitlines(), ""]:
        if not line:
            if current:
                events.append(current)
                current = {}
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "data":
            current["data"] = json.loads(value)
        elif name == "id":
            current["id"] = int(value)
        else:
            current[name] = value
    return events


def wait_until(predicate: Any, *, timeout: float = 60, what: str = "condition", step: float = 0.05) -> Any:
    """Poll ``predicate`` every ``step`` seconds until it returns something truthy (returned);
    `AssertionError` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(step)
