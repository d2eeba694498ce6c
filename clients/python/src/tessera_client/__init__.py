"""A client of the Tessera render farm's HTTP API (``/api/v1``), standard library
only: submit a scene with its files, wait with progress, fetch images and frames,
follow the farm's events, and every control of jobs and workers.

    from tessera_client import Client

    farm = Client("https://render-1:8080", token_file="client.token",
                  tls_fingerprint="3f1e...")
    job = farm.submit("scenes/instances.json", width=640, height=400)
    job = farm.wait(job.id, progress=lambda j: print(j.tiles_done, "/", j.tiles_total))
    farm.image(job.id, "instances.png")
"""

from .client import MAX_CHUNK, Client, TesseraError, file_key, normalize_fingerprint
from .types import (
    FINAL_STATES,
    Asset,
    Cancelled,
    Event,
    EventJob,
    FileKey,
    FrameFailure,
    Frames,
    GapEvent,
    Job,
    LogEntry,
    Resolution,
    StreamEvent,
    UploadProgress,
    Worker,
)

__version__ = "0.1.0"

__all__ = [
    "Asset",
    "Cancelled",
    "Client",
    "Event",
    "EventJob",
    "FINAL_STATES",
    "FileKey",
    "FrameFailure",
    "Frames",
    "GapEvent",
    "Job",
    "LogEntry",
    "MAX_CHUNK",
    "Resolution",
    "StreamEvent",
    "TesseraError",
    "UploadProgress",
    "Worker",
    "file_key",
    "normalize_fingerprint",
]
