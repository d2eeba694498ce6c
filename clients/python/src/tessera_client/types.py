"""The JSON objects of the HTTP API as typed dataclasses.

Each keeps the whole object it was read from in ``raw``, so that a field the
coordinator adds later is still there to read before this module names it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

JsonObject = Dict[str, Any]

#: The states a job ends in.
FINAL_STATES = frozenset({"done", "failed", "cancelled"})


def _int(d: Mapping[str, Any], key: str, default: int = 0) -> int:
    value = d.get(key)
    return int(value) if value is not None else default


def _opt_int(d: Mapping[str, Any], key: str) -> Optional[int]:
    value = d.get(key)
    return int(value) if value is not None else None


def _opt_float(d: Mapping[str, Any], key: str) -> Optional[float]:
    value = d.get(key)
    return float(value) if value is not None else None


def _opt_str(d: Mapping[str, Any], key: str) -> Optional[str]:
    value = d.get(key)
    return str(value) if value is not None else None


@dataclass(frozen=True)
class FrameFailure:
    """A sequence's frame that failed: its number, its frame job, the error."""

    frame: int
    job: int
    error: str


@dataclass(frozen=True)
class Frames:
    """A sequence job's frames (``frames`` of a job's JSON)."""

    first: int
    last: int
    done: int
    active: int
    pending: int
    cancelled: int
    failed: int
    done_prefix: int
    failures: List[FrameFailure]

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Frames":
        return cls(
            first=_int(d, "first"),
            last=_int(d, "last"),
            done=_int(d, "done"),
            active=_int(d, "active"),
            pending=_int(d, "pending"),
            cancelled=_int(d, "cancelled"),
            failed=_int(d, "failed"),
            done_prefix=_int(d, "done_prefix"),
            failures=[
                FrameFailure(frame=_int(f, "frame"), job=_int(f, "job"), error=str(f.get("error", "")))
                for f in d.get("failures") or []
            ],
        )


@dataclass(frozen=True)
class Job:
    """A job's status, as ``tessera status --json`` prints it and ``GET
    /api/v1/jobs/{id}`` answers it. ``state`` is one of queued, running, paused,
    waiting (for the jobs it was submitted ``after``: those not yet done are in
    ``waiting_for``), done, failed or cancelled."""

    id: int
    state: str
    paused: bool
    name: str
    submitter: str
    submitted_from: str
    submitted_unix_ms: int
    priority: int
    frame: int
    width: int
    height: int
    aa: int
    max_depth: int
    tiles_done: int
    tiles_total: int
    rays: int
    elapsed_ms: int
    eta_ms: Optional[int]
    error: Optional[str]
    warning: Optional[str]
    sampler: str
    target_error: Optional[float]
    samples: int
    samples_per_pixel: Optional[float]
    estimated_error: Optional[float]
    time_limit_ms: Optional[int]
    stopped_on_time_limit: bool
    queued_ms: Optional[int]
    sequence: Optional[int]
    frames: Optional[Frames]
    asset_files: int
    asset_bytes: int
    after: Tuple[int, ...]
    waiting_for: Tuple[int, ...]
    raw: JsonObject = field(repr=False, compare=False)

    @property
    def ended(self) -> bool:
        """Whether the job is done, failed or cancelled."""
        return self.state in FINAL_STATES

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Job":
        frames = d.get("frames")
        assets = d.get("assets") or {}
        return cls(
            id=_int(d, "id"),
            state=str(d.get("state", "")),
            paused=bool(d.get("paused", False)),
            name=str(d.get("name", "")),
            submitter=str(d.get("submitter", "")),
            submitted_from=str(d.get("submitted_from", "")),
            submitted_unix_ms=_int(d, "submitted_unix_ms"),
            priority=_int(d, "priority"),
            frame=_int(d, "frame", 1),
            width=_int(d, "width"),
            height=_int(d, "height"),
            aa=_int(d, "aa"),
            max_depth=_int(d, "max_depth"),
            tiles_done=_int(d, "tiles_done"),
            tiles_total=_int(d, "tiles_total"),
            rays=_int(d, "rays"),
            elapsed_ms=_int(d, "elapsed_ms"),
            eta_ms=_opt_int(d, "eta_ms"),
            error=_opt_str(d, "error"),
            warning=_opt_str(d, "warning"),
            sampler=str(d.get("sampler", "")),
            target_error=_opt_float(d, "target_error"),
            samples=_int(d, "samples"),
            samples_per_pixel=_opt_float(d, "samples_per_pixel"),
            estimated_error=_opt_float(d, "estimated_error"),
            time_limit_ms=_opt_int(d, "time_limit_ms"),
            stopped_on_time_limit=bool(d.get("stopped_on_time_limit", False)),
            queued_ms=_opt_int(d, "queued_ms"),
            sequence=_opt_int(d, "sequence"),
            frames=Frames.from_json(frames) if isinstance(frames, Mapping) else None,
            asset_files=_int(assets, "files"),
            asset_bytes=_int(assets, "bytes"),
            after=tuple(int(j) for j in d.get("after") or ()),
            waiting_for=tuple(int(j) for j in d.get("waiting_for") or ()),
            raw=dict(d),
        )


@dataclass(frozen=True)
class Worker:
    """A connected worker, as ``tessera workers --json`` lists it. ``key`` and
    ``cache`` are left as the JSON objects they are (or None)."""

    id: int
    name: str
    host: str
    threads: int
    tiles_in_flight: int
    tiles_done: int
    rays: int
    connected_ms: int
    rays_per_second: float
    build: str
    quarantined: Optional[str]
    rtt_us: Optional[int]
    credit: int
    draining: bool
    disabled: bool
    unresponsive: bool
    key: Optional[JsonObject]
    cache: Optional[JsonObject]
    raw: JsonObject = field(repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Worker":
        return cls(
            id=_int(d, "id"),
            name=str(d.get("name", "")),
            host=str(d.get("host", "")),
            threads=_int(d, "threads"),
            tiles_in_flight=_int(d, "tiles_in_flight"),
            tiles_done=_int(d, "tiles_done"),
            rays=_int(d, "rays"),
            connected_ms=_int(d, "connected_ms"),
            rays_per_second=float(d.get("rays_per_second") or 0.0),
            build=str(d.get("build", "")),
            quarantined=_opt_str(d, "quarantined"),
            rtt_us=_opt_int(d, "rtt_us"),
            credit=_int(d, "credit"),
            draining=bool(d.get("draining", False)),
            disabled=bool(d.get("disabled", False)),
            unresponsive=bool(d.get("unresponsive", False)),
            key=d.get("key"),
            cache=d.get("cache"),
            raw=dict(d),
        )


@dataclass(frozen=True)
class Cancelled:
    """The answer to a cancel: ``already_cancelled`` when it was so before."""

    id: int
    already_cancelled: bool


@dataclass(frozen=True)
class LogEntry:
    """An entry of a job's own event log (``GET /api/v1/jobs/{id}/events``, as
    ``tessera events --json``): its sequence number, time, event and detail."""

    seq: int
    unix_ms: int
    event: str
    detail: str

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "LogEntry":
        return cls(
            seq=_int(d, "seq"),
            unix_ms=_int(d, "unix_ms"),
            event=str(d.get("event", "")),
            detail=str(d.get("detail", "")),
        )


@dataclass(frozen=True)
class FileKey:
    """A file of the coordinator's store: its SHA-256 (hex) and size in bytes, and
    (where the answer says it) how many of its bytes the store has received."""

    sha256: str
    size: int
    received: int = 0


@dataclass(frozen=True)
class Asset:
    """A file a job names: the name the scene uses, its SHA-256 and size."""

    name: str
    sha256: str
    size: int

    def to_json(self) -> JsonObject:
        return {"name": self.name, "sha256": self.sha256, "size": self.size}


@dataclass(frozen=True)
class Resolution:
    """``POST /api/v1/resolve``'s answer: ``files``, those given that the scene
    reads; ``missing``, names it reads that were not given; ``lacking``, files the
    store lacks (with ``received``); ``complete`` once neither is left."""

    files: List[Asset]
    missing: List[str]
    lacking: List[FileKey]
    complete: bool

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Resolution":
        return cls(
            files=[Asset(str(f["name"]), str(f["sha256"]), int(f["size"])) for f in d.get("files") or []],
            missing=[str(m) for m in d.get("missing") or []],
            lacking=[
                FileKey(str(k["sha256"]), int(k["size"]), int(k.get("received") or 0))
                for k in d.get("lacking") or []
            ],
            complete=bool(d.get("complete", False)),
        )


@dataclass(frozen=True)
class UploadProgress:
    """What an upload's chunk did, for ``submit(on_upload=...)``: the file's name
    (or path), key, the offset the chunk was sent at, and how many bytes the store
    has once it is in."""

    name: str
    sha256: str
    size: int
    offset: int
    received: int
    complete: bool


@dataclass(frozen=True)
class EventJob:
    """The ``job`` object of a farm event: its id, and the details its kind has
    (``name``, ``detail``, ``frame``, ``frame_job``)."""

    id: int
    name: Optional[str]
    detail: Optional[str]
    frame: Optional[int]
    frame_job: Optional[int]
    raw: JsonObject = field(repr=False, compare=False)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "EventJob":
        return cls(
            id=_int(d, "id"),
            name=_opt_str(d, "name"),
            detail=_opt_str(d, "detail"),
            frame=_opt_int(d, "frame"),
            frame_job=_opt_int(d, "frame_job"),
            raw=dict(d),
        )


@dataclass(frozen=True)
class Event:
    """A farm event of ``GET /api/v1/events`` (docs/events.md): its id, kind
    (submitted, started, done, joined, left, ...), time, and the ``job`` and/or
    ``worker`` it is about (the worker as its JSON object: id, name, host, ...)."""

    id: int
    kind: str
    unix_ms: int
    job: Optional[EventJob]
    worker: Optional[JsonObject]
    data: JsonObject = field(repr=False, compare=False)


@dataclass(frozen=True)
class GapEvent:
    """The stream's ``gap`` event: the events after ``after`` and before
    ``oldest_kept`` are no longer kept, and the stream goes on from
    ``oldest_kept``. Its ``id`` is ``oldest_kept - 1``. It is about no job and no
    worker: ``job`` and ``worker`` are None, as a loop over the stream reads them."""

    id: int
    after: int
    oldest_kept: int
    message: str
    data: JsonObject = field(repr=False, compare=False)
    kind: str = "gap"
    job: Optional[EventJob] = None
    worker: Optional[JsonObject] = None


#: What :meth:`tessera_client.Client.events` yields.
StreamEvent = Union[Event, GapEvent]


def stream_event(event_id: int, kind: str, data: Mapping[str, Any]) -> StreamEvent:
    """A stream's event as its typed object."""
    if kind == "gap":
        return GapEvent(
            id=event_id,
            after=_int(data, "after"),
            oldest_kept=_int(data, "oldest_kept"),
            message=str(data.get("message", "")),
            data=dict(data),
        )
    job = data.get("job")
    worker = data.get("worker")
    return Event(
        id=event_id,
        kind=kind,
        unix_ms=_int(data, "unix_ms"),
        job=EventJob.from_json(job) if isinstance(job, Mapping) else None,
        worker=dict(worker) if isinstance(worker, Mapping) else None,
        data=dict(data),
    )
