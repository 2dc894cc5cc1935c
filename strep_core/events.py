"""Typed progress events and the sink interface through which methods report them.

Every event is a pydantic model with a ``kind`` tag, so it serialises to JSON as is
(``event.model_dump_json()``) and parses back with `parse_event`. Methods never know who
listens: they call ``sink.emit(event)``; the CLI, the job service and the viewers are sinks.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Annotated, Any, Literal, Protocol, get_args, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

from strep_core.errors import Cancelled


class _Event(BaseModel):
    model_config = ConfigDict(frozen=True)


class StartEvent(_Event):
    """A run begins."""

    kind: Literal["start"] = "start"
    method: str
    sequence: str
    frames: int
    dims: int
    unit: str
    total_iterations: int = Field(description="iterations planned (frames for incremental methods)")
    initial_guess: str


class IterationEvent(_Event):
    """Progress of an iterative method, emitted every ``event_interval`` iterations."""

    kind: Literal["iteration"] = "iteration"
    iteration: int = Field(description="iterations done so far (0: the starting poses, before any step)")
    total: int
    elapsed: float = Field(description="seconds since the run started")
    losses: dict[str, float] = Field(default_factory=dict, description="loss terms, 'total' included")
    poses: list[list[float]] | None = Field(
        default=None,
        description="current pose vector per frame: (x, y, theta) in 2D, (t, axis-angle) in 3D",
    )
    ate: float | None = Field(default=None, description="current ATE in the sequence unit")


class StageEvent(_Event):
    """A named stage of a run starts: ``load`` (reading the input), ``init:<method>`` (the
    warm start, e.g. ``init:multiway``), ``write`` (the result files). The optimisation itself
    is announced by its `IterationEvent` s (iteration 0: the starting poses and their ATE)."""

    kind: Literal["stage"] = "stage"
    stage: str
    elapsed: float
    done: int | None = Field(default=None, description="a long stage's progress (the warm start's steps)")
    total: int | None = Field(default=None, description="steps of the stage, with ``done``")


STAGE_LABELS = {
    "load": "loading the sequence",
    "init": "warm start",
    "prepare": "preparing the optimisation",  # (viewers: after the start event, before iteration 0)
    "optimise": "optimising",  # (viewers: from the first iteration event after iteration 0)
    "write": "writing files",
}


def stage_label(stage: str) -> str:
    """A stage's name for people: ``"init:multiway"`` -> ``"warm start (multiway)"``."""
    head, _, detail = stage.partition(":")
    label = STAGE_LABELS.get(head, head)
    return f"{label} ({detail})" if detail else label


class ResultEvent(_Event):
    """The run finished; carries its metrics and final poses."""

    kind: Literal["result"] = "result"
    method: str
    metrics: dict[str, float | int | str | None]
    poses: list[list[float]]
    iterations: int
    wall_seconds: float


# The one list of event kinds: a new kind is a class above, a member of this union and a
# reducer in `strep_core.runstate.REDUCERS` (docs/design/extending.md).
Event = Annotated[StartEvent | IterationEvent | StageEvent | ResultEvent, Field(discriminator="kind")]
_ADAPTER: TypeAdapter[Event] = TypeAdapter(Event)

#: The kinds of progress events (the job store also keeps ``status`` records, which are not).
PROGRESS_KINDS: frozenset[str] = frozenset(t.model_fields["kind"].default for t in get_args(get_args(Event)[0]))


def parse_event(data: str | bytes | dict[str, object]) -> Event:
    """Parse an event from its JSON text or dict."""
    if isinstance(data, dict):
        return _ADAPTER.validate_python(data)
    return _ADAPTER.validate_json(data)


def progress_events(items: Iterable[Any]) -> Iterator[Event]:
    """Events from a stored log: `Event` objects, dicts, JSON text, or records with ``kind``
    and ``data`` (the job store's ``StoredEvent``). Entries of other kinds (``status``...) are
    skipped; a malformed progress event raises ``pydantic.ValidationError``."""
    for item in items:
        if isinstance(item, (str, bytes)):
            item = json.loads(item)
        elif hasattr(item, "data") and hasattr(item, "kind") and not isinstance(item, Mapping):
            if item.kind not in PROGRESS_KINDS:
                continue
            item = json.loads(item.data)
        if isinstance(item, Mapping):
            if item.get("kind") not in PROGRESS_KINDS:
                continue
            yield parse_event(dict(item))
        elif getattr(item, "kind", None) in PROGRESS_KINDS:
            yield item


def pose_list(pose_vectors: np.ndarray) -> list[list[float]]:
    """``(K, 3|6)`` pose vectors -> nested lists of floats, rounded for compact JSON."""
    return np.round(np.asarray(pose_vectors, dtype=np.float64), 6).tolist()


# --------------------------------------------------------------------------------------------
# Sinks


@runtime_checkable
class Sink(Protocol):
    """Receives events. ``emit`` must return quickly and never raise into the method."""

    def emit(self, event: Event) -> None: ...


class NullSink:
    """Drops every event (the default)."""

    def emit(self, event: Event) -> None:
        return None


class ListSink:
    """Keeps every event in order, for tests and replays."""

    def __init__(self) -> None:
        self.events: list[Event] = []

    def emit(self, event: Event) -> None:
        self.events.append(event)

    def of_kind(self, kind: str) -> list[Event]:
        return [e for e in self.events if e.kind == kind]


class CallbackSink:
    """Calls a function with every event."""

    def __init__(self, fn: Callable[[Event], None]) -> None:
        self.fn = fn

    def emit(self, event: Event) -> None:
        self.fn(event)


class MultiSink:
    """Forwards every event to several sinks."""

    def __init__(self, sinks: Iterable[Sink]) -> None:
        self.sinks = list(sinks)

    def emit(self, event: Event) -> None:
        for sink in self.sinks:
            sink.emit(event)


# --------------------------------------------------------------------------------------------
# Cancellation


class CancelFlag(Protocol):
    def is_set(self) -> bool: ...


class CancelToken:
    """A thread-safe cancel flag (same interface as `threading.Event`)."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def set(self) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()


def check_cancel(cancel: CancelFlag | None) -> None:
    """Raise `Cancelled` if the flag is set. Methods call this between iterations."""
    if cancel is not None and cancel.is_set():
        raise Cancelled("the run was cancelled")
