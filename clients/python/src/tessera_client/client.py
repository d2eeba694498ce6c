"""The client of the coordinator's HTTP API (``/api/v1``, docs/api.md)."""

from __future__ import annotations

import hashlib
import http.client
import json
import os
import ssl
import time
import urllib.parse
from pathlib import Path
from typing import (
    Any,
    Callable,
    Dict,
    Iterable,
    Iterator,
    List,
    Mapping,
    Optional,
    Sequence,
    Tuple,
    Union,
)

from .types import (
    Asset,
    Cancelled,
    FileKey,
    Job,
    JsonObject,
    LogEntry,
    Resolution,
    StreamEvent,
    UploadProgress,
    Worker,
    stream_event,
)

PathLike = Union[str, "os.PathLike[str]"]

#: The most bytes one upload request may carry (the coordinator's bound).
MAX_CHUNK = 8 * 1024 * 1024

#: The longest the coordinator holds a ``/wait`` request, in seconds.
MAX_WAIT = 10

#: How many times a submission is sent again after the store lost a file.
SUBMIT_ATTEMPTS = 4

#: The most rounds of resolve and upload a scene may take (a glTF's buffers are
#: named once the glTF is stored: two rounds; more means something is wrong).
RESOLVE_ROUNDS = 8

_API = "/api/v1"


class TesseraError(Exception):
    """Anything the coordinator refused, or a failure to reach it.

    ``kind`` is the refusal's kind as the API gives it (``invalid``, ``not_found``,
    ``state``, ``limit``, ``unavailable``, ``unauthorized``, ``forbidden``,
    ``lacking``, ``internal``), or one of the client's own: ``connection`` (the
    coordinator could not be reached or cut the connection), ``tls`` (its
    certificate is not the one pinned), ``timeout`` (a wait ran out), ``protocol``
    (an answer that is not what the API answers), ``missing_file`` (a file the
    scene names is not on this machine). ``status`` is the HTTP status, or None
    when there was no answer. ``body`` is the error's whole JSON object.
    """

    def __init__(
        self,
        message: str,
        kind: str,
        status: Optional[int] = None,
        body: Optional[JsonObject] = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.kind = kind
        self.status = status
        self.body: JsonObject = body if body is not None else {}

    @property
    def lacking(self) -> List[FileKey]:
        """For ``kind == "lacking"``: the files the store lacks."""
        return [FileKey(str(k["sha256"]), int(k["size"])) for k in self.body.get("lacking") or []]

    def __str__(self) -> str:
        if self.status is not None:
            return f"{self.message} ({self.kind}, HTTP {self.status})"
        return f"{self.message} ({self.kind})"


def normalize_fingerprint(fingerprint: str) -> str:
    """A SHA-256 fingerprint as 64 lower-case hex digits, from any case, with or
    without colons (the form ``openssl x509 -fingerprint -sha256`` prints)."""
    digits = fingerprint.strip().replace(":", "").lower()
    if len(digits) != 64 or any(c not in "0123456789abcdef" for c in digits):
        raise ValueError(
            f"a TLS fingerprint is 64 hex digits (SHA-256, colons allowed), not {fingerprint!r}"
        )
    return digits


def file_key(path: PathLike) -> FileKey:
    """The SHA-256 and size of a file, as the coordinator's store names it."""
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while True:
            block = f.read(1 << 20)
            if not block:
                break
            digest.update(block)
            size += len(block)
    return FileKey(digest.hexdigest(), size)


class _PinnedConnection(http.client.HTTPSConnection):
    """HTTPS whose server certificate must have one SHA-256 fingerprint: checked
    right after the handshake, before anything is sent."""

    def __init__(self, host: str, port: Optional[int], pin: str, timeout: float) -> None:
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        # The pin replaces the chain and the name: this certificate and no other. The
        # handshake's signatures are still checked, so only its key's holder passes.
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
        super().__init__(host, port, timeout=timeout, context=context)
        self._pin = pin

    def connect(self) -> None:
        super().connect()
        assert isinstance(self.sock, ssl.SSLSocket)
        der = self.sock.getpeercert(binary_form=True)
        presented = hashlib.sha256(der).hexdigest() if der else "(none)"
        if presented != self._pin:
            self.sock.close()
            self.sock = None
            raise TesseraError(
                f"TLS with the coordinator at {self.host}:{self.port}: the coordinator "
                f"presented the certificate with SHA-256 fingerprint {presented}, but "
                f"tls_fingerprint expects {self._pin}; refusing it (nothing was sent)",
                "tls",
            )


Progress = Callable[[Job], None]
UploadCallback = Callable[[UploadProgress], None]


class Client:
    """A client of one coordinator's HTTP API.

    ``url`` is the coordinator's HTTP address (``--http``): ``http://HOST:PORT``,
    ``https://HOST:PORT`` or ``HOST:PORT`` (then HTTPS when a fingerprint or a CA
    file is given), with an optional path prefix for a proxy. Where an argument is
    None the environment gives it: ``TESSERA_URL``, ``TESSERA_TOKEN`` (the token
    itself) or ``TESSERA_TOKEN_FILE``, ``TESSERA_TLS_FINGERPRINT`` (empty counts
    as unset) and ``TESSERA_TLS_CA``; ``use_env=False`` reads none of them.

    ``tls_fingerprint`` pins the coordinator's certificate (``--tls-auto`` prints
    it): 64 hex digits, any case, colons allowed. ``ca_file`` instead trusts the
    certificates of a PEM file, with the usual checks of the chain and the name.
    ``timeout`` bounds each request's connection and reads, in seconds.
    """

    def __init__(
        self,
        url: Optional[str] = None,
        token: Optional[str] = None,
        token_file: Optional[PathLike] = None,
        tls_fingerprint: Optional[str] = None,
        ca_file: Optional[PathLike] = None,
        timeout: float = 60.0,
        use_env: bool = True,
    ) -> None:
        env: Mapping[str, str] = os.environ if use_env else {}
        url = url or env.get("TESSERA_URL")
        if not url:
            raise ValueError("no coordinator URL: give url= or set TESSERA_URL")
        if token is None and token_file is None:
            token = env.get("TESSERA_TOKEN") or None
            token_file = env.get("TESSERA_TOKEN_FILE") or None
        if token is None and token_file is not None:
            token = Path(token_file).read_text(encoding="utf-8").strip()
            if not token:
                raise ValueError(f"the token file {token_file} is empty")
        if tls_fingerprint is None:
            tls_fingerprint = env.get("TESSERA_TLS_FINGERPRINT") or None
        if ca_file is None:
            ca_file = env.get("TESSERA_TLS_CA") or None
        self.token: Optional[str] = token.strip() if token else None
        self.fingerprint = normalize_fingerprint(tls_fingerprint) if tls_fingerprint else None
        self.timeout = timeout

        tls_wanted = self.fingerprint is not None or ca_file is not None
        if "://" not in url:
            url = ("https://" if tls_wanted else "http://") + url
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"not an http:// or https:// URL: {url!r}")
        if tls_wanted and parts.scheme != "https":
            raise ValueError(f"a TLS fingerprint or CA file needs an https:// URL, not {url!r}")
        self.url = url
        self._https = parts.scheme == "https"
        self._host = parts.hostname
        self._port = parts.port
        self._prefix = parts.path.rstrip("/")
        self._context: Optional[ssl.SSLContext] = None
        if ca_file is not None:
            self._context = ssl.create_default_context(cafile=str(ca_file))
        elif self._https and self.fingerprint is None:
            self._context = ssl.create_default_context()

    # ----------------------------------------------------------------- transport

    def _connection(self, timeout: float) -> http.client.HTTPConnection:
        if self.fingerprint is not None:
            return _PinnedConnection(self._host, self._port, self.fingerprint, timeout)
        if self._https:
            return http.client.HTTPSConnection(
                self._host, self._port, timeout=timeout, context=self._context
            )
        return http.client.HTTPConnection(self._host, self._port, timeout=timeout)

    def _target(self, path: str, query: Optional[Mapping[str, Any]] = None) -> str:
        target = self._prefix + _API + path
        if query:
            pairs = [(k, str(v).lower() if isinstance(v, bool) else str(v)) for k, v in query.items() if v is not None]
            if pairs:
                target += "?" + urllib.parse.urlencode(pairs)
        return target

    def _headers(self, extra: Optional[Mapping[str, str]] = None) -> Dict[str, str]:
        headers = {"User-Agent": "tessera-client-python/0.1", "Accept": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        if extra:
            headers.update(extra)
        return headers

    def _open(
        self,
        method: str,
        path: str,
        query: Optional[Mapping[str, Any]] = None,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        headers: Optional[Mapping[str, str]] = None,
        timeout: Optional[float] = None,
    ) -> Tuple[http.client.HTTPConnection, http.client.HTTPResponse]:
        """Sends a request: the connection and its answer's head (status < 400), or
        TesseraError with the refusal read from its body."""
        target = self._target(path, query)
        extra = dict(headers or {})
        if content_type:
            extra["Content-Type"] = content_type
        conn = self._connection(timeout if timeout is not None else self.timeout)
        try:
            conn.request(method, target, body=body, headers=self._headers(extra))
            response = conn.getresponse()
        except TesseraError:
            conn.close()
            raise
        except ssl.SSLError as e:
            conn.close()
            raise TesseraError(f"TLS with the coordinator at {self._where()}: {e}", "tls") from e
        except (OSError, http.client.HTTPException) as e:
            conn.close()
            raise TesseraError(
                f"{method} {target}: cannot reach the coordinator at {self._where()}: {e}",
                "connection",
            ) from e
        if response.status >= 400:
            try:
                text = response.read()
            except (OSError, http.client.HTTPException):
                text = b""
            finally:
                conn.close()
            raise _refusal(method, target, response.status, text)
        return conn, response

    def _where(self) -> str:
        return f"{self._host}:{self._port}" if self._port else self._host

    def _call(
        self,
        method: str,
        path: str,
        query: Optional[Mapping[str, Any]] = None,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        timeout: Optional[float] = None,
    ) -> Tuple[int, bytes]:
        conn, response = self._open(method, path, query, body, content_type, timeout=timeout)
        try:
            return response.status, response.read()
        except (OSError, http.client.HTTPException) as e:
            raise TesseraError(f"{method} {path}: the answer was cut short: {e}", "connection") from e
        finally:
            conn.close()

    def _json(
        self,
        method: str,
        path: str,
        query: Optional[Mapping[str, Any]] = None,
        body: Optional[Mapping[str, Any]] = None,
        timeout: Optional[float] = None,
    ) -> Any:
        data = None
        content_type = None
        if method != "GET":
            data = json.dumps(dict(body or {})).encode()
            content_type = "application/json"
        _, text = self._call(method, path, query, data, content_type, timeout)
        try:
            return json.loads(text)
        except ValueError as e:
            raise TesseraError(f"{method} {path}: the answer is not JSON: {text[:200]!r}", "protocol") from e

    # ---------------------------------------------------------------- jobs

    def job(self, job_id: int) -> Job:
        """A job's status."""
        return Job.from_json(self._json("GET", f"/jobs/{int(job_id)}"))

    def jobs(
        self,
        state: Optional[str] = None,
        name: Optional[str] = None,
        submitter: Optional[str] = None,
        limit: Optional[int] = None,
        page_size: int = 100,
    ) -> Iterator[Job]:
        """The jobs, newest first, read a page at a time as they are iterated:
        those in ``state`` (queued, running, paused, done, failed, cancelled), whose
        name and submitter contain the texts given, at most ``limit`` of them."""
        before: Optional[int] = None
        given = 0
        while True:
            size = page_size if limit is None else min(page_size, limit - given)
            if size <= 0:
                return
            page = self._json(
                "GET",
                "/jobs",
                {"state": state, "name": name, "submitter": submitter, "before": before, "limit": size},
            )
            for entry in page.get("jobs") or []:
                yield Job.from_json(entry)
                given += 1
            before = page.get("next")
            if before is None:
                return

    def wait(
        self,
        job_id: int,
        progress: Optional[Progress] = None,
        timeout: Optional[float] = None,
    ) -> Job:
        """Waits for a job to end (done, failed or cancelled) and returns its status,
        following it with ``/wait`` long polls. ``progress`` is called with the
        status at once, then each time a tile is done or its state changes.
        ``timeout`` (seconds, None for no bound) raises TesseraError ``timeout``."""
        deadline = None if timeout is None else time.monotonic() + timeout
        job = self.job(job_id)
        if progress is not None:
            progress(job)
        while not job.ended:
            hold = MAX_WAIT
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TesseraError(
                        f"job {job_id} is still {job.state} after {timeout} s "
                        f"({job.tiles_done} of {job.tiles_total} tiles)",
                        "timeout",
                    )
                hold = max(0, min(MAX_WAIT, int(left + 0.999)))
            query: Dict[str, Any] = {"timeout": hold}
            if progress is not None:
                query["after_tiles"] = job.tiles_done
            answer = Job.from_json(
                self._json("GET", f"/jobs/{int(job_id)}/wait", query, timeout=self.timeout + hold)
            )
            changed = (answer.state, answer.tiles_done, answer.paused) != (job.state, job.tiles_done, job.paused)
            job = answer
            if progress is not None and changed:
                progress(job)
        return job

    def image_bytes(self, job_id: int) -> bytes:
        """A finished job's image, as PNG bytes (``state`` 409 before it is done)."""
        return self._call("GET", f"/jobs/{int(job_id)}/image.png")[1]

    def image(self, job_id: int, path: PathLike) -> Path:
        """Writes a finished job's image to ``path`` (a PNG) and returns the path."""
        return _write(path, self.image_bytes(job_id))

    def frame_bytes(self, job_id: int, frame: int) -> bytes:
        """Frame ``frame`` of a sequence job, once done, as PNG bytes."""
        return self._call("GET", f"/jobs/{int(job_id)}/frames/{int(frame)}")[1]

    def frame(self, job_id: int, frame: int, path: PathLike) -> Path:
        """Writes frame ``frame`` of a sequence job to ``path`` and returns it."""
        return _write(path, self.frame_bytes(job_id, frame))

    def job_events(self, job_id: int, after: int = 0) -> Iterator[LogEntry]:
        """A job's own event log (its tiles too), after entry ``after``."""
        while True:
            page = self._json("GET", f"/jobs/{int(job_id)}/events", {"after": after})
            if not page:
                return
            for entry in page:
                item = LogEntry.from_json(entry)
                after = max(after, item.seq)
                yield item

    # ------------------------------------------------------------- controls

    def pause(self, job_id: int) -> Job:
        return Job.from_json(self._json("POST", f"/jobs/{int(job_id)}/pause"))

    def resume(self, job_id: int) -> Job:
        return Job.from_json(self._json("POST", f"/jobs/{int(job_id)}/resume"))

    def priority(self, job_id: int, priority: int) -> Job:
        """Gives a job a new priority (higher runs first)."""
        return Job.from_json(self._json("POST", f"/jobs/{int(job_id)}/priority", body={"priority": int(priority)}))

    def cancel(self, job_id: int) -> Cancelled:
        """Cancels a job; one already cancelled is no error (``already_cancelled``)."""
        answer = self._json("POST", f"/jobs/{int(job_id)}/cancel")
        return Cancelled(id=int(answer["id"]), already_cancelled=bool(answer.get("already_cancelled")))

    def retry(self, job_id: int, frame: Optional[int] = None) -> Job:
        """Puts a failed or cancelled job, or a sequence's frame, back in the queue."""
        body = {} if frame is None else {"frame": int(frame)}
        return Job.from_json(self._json("POST", f"/jobs/{int(job_id)}/retry", body=body))

    def requeue(self, job_id: int, tiles: Iterable[int]) -> Job:
        """Renders tiles of a job again."""
        return Job.from_json(self._json("POST", f"/jobs/{int(job_id)}/requeue", body={"tiles": [int(t) for t in tiles]}))

    def refine(
        self,
        job_id: int,
        target_error: float,
        aa: Optional[int] = None,
        time_limit_ms: Optional[int] = None,
    ) -> Job:
        """A new adaptive job from a finished one, to ``target_error`` (8-bit
        levels): the new job's status."""
        body: Dict[str, Any] = {"target_error": float(target_error)}
        if aa is not None:
            body["aa"] = int(aa)
        if time_limit_ms is not None:
            body["time_limit_ms"] = int(time_limit_ms)
        answer = self._json("POST", f"/jobs/{int(job_id)}/refine", body=body)
        return self.job(int(answer["id"]))

    def delete(self, job_id: int) -> None:
        """Deletes an ended job (and its image)."""
        self._json("POST", f"/jobs/{int(job_id)}/delete")

    def workers(self) -> List[Worker]:
        """The connected workers."""
        return [Worker.from_json(w) for w in self._json("GET", "/workers")]

    def _worker_control(self, worker: Union[int, str], action: str) -> List[Worker]:
        name = urllib.parse.quote(str(worker), safe="")
        return [Worker.from_json(w) for w in self._json("POST", f"/workers/{name}/{action}")]

    def drain_worker(self, worker: Union[int, str]) -> List[Worker]:
        """Has a worker (by id or name) finish its tiles, then leave."""
        return self._worker_control(worker, "drain")

    def disable_worker(self, worker: Union[int, str]) -> List[Worker]:
        """Gives a worker (by id, or a machine by name) no more tiles."""
        return self._worker_control(worker, "disable")

    def enable_worker(self, worker: Union[int, str]) -> List[Worker]:
        """Enables a disabled worker (or machine) again."""
        return self._worker_control(worker, "enable")

    # ------------------------------------------------------------ submitting

    def resolve(self, scene: Union[str, Mapping[str, Any]], assets: Sequence[Asset] = ()) -> Resolution:
        """Which files a scene reads, by the renderer's rules."""
        body = {"scene": scene, "assets": [a.to_json() for a in assets]}
        return Resolution.from_json(self._json("POST", "/resolve", body=body))

    def lacking(self, keys: Sequence[FileKey]) -> List[FileKey]:
        """Of ``keys``, those the store lacks, each with the bytes it has of it."""
        answer = self._json(
            "POST", "/files/lacking", body={"files": [{"sha256": k.sha256, "size": k.size} for k in keys]}
        )
        return [FileKey(str(k["sha256"]), int(k["size"]), int(k.get("received") or 0)) for k in answer.get("lacking") or []]

    def upload(
        self,
        path: PathLike,
        key: Optional[FileKey] = None,
        offset: Optional[int] = None,
        chunk_size: int = MAX_CHUNK,
        max_chunks: Optional[int] = None,
        on_upload: Optional[UploadCallback] = None,
        name: Optional[str] = None,
    ) -> int:
        """Uploads a file to the store in chunks of at most ``chunk_size`` bytes,
        from ``offset`` (by default where the store's upload stands, as
        ``files/lacking`` says), each chunk at the offset where the last one
        stopped. Stops after ``max_chunks`` chunks if given. Returns how many bytes
        of it the store has (its size once complete)."""
        if not 0 < chunk_size <= MAX_CHUNK:
            raise ValueError(f"chunk_size is from 1 to {MAX_CHUNK} bytes, not {chunk_size}")
        key = key or file_key(path)
        if offset is None:
            lacking = [k for k in self.lacking([key]) if k.sha256 == key.sha256 and k.size == key.size]
            if not lacking:
                return key.size
            offset = lacking[0].received
        sent = 0
        received = offset
        with open(path, "rb") as f:
            while received < key.size or key.size == 0:
                if max_chunks is not None and sent >= max_chunks:
                    break
                f.seek(received)
                chunk = f.read(chunk_size)
                if len(chunk) == 0 and key.size > 0:
                    raise TesseraError(f"{path} is shorter than its {key.size} bytes: did it change?", "missing_file")
                answer = self._json_bytes("PUT", f"/files/{key.sha256}-{key.size}", {"offset": received}, chunk)
                now = int(answer.get("received", received))
                complete = bool(answer.get("complete"))
                if on_upload is not None:
                    on_upload(UploadProgress(name or str(path), key.sha256, key.size, received, now, complete))
                sent += 1
                if complete:
                    return key.size
                if now <= received:
                    raise TesseraError(
                        f"the upload of {path} does not move on from byte {received}", "protocol", body=answer
                    )
                received = now
        return received

    def _json_bytes(self, method: str, path: str, query: Mapping[str, Any], data: bytes) -> JsonObject:
        _, text = self._call(method, path, query, data, "application/octet-stream")
        try:
            answer = json.loads(text)
        except ValueError as e:
            raise TesseraError(f"{method} {path}: the answer is not JSON: {text[:200]!r}", "protocol") from e
        if not isinstance(answer, dict):
            raise TesseraError(f"{method} {path}: the answer is not a JSON object", "protocol")
        return answer

    def submit(
        self,
        scene: Union[PathLike, Mapping[str, Any]],
        base_dir: Optional[PathLike] = None,
        *,
        name: Optional[str] = None,
        submitter: Optional[str] = None,
        priority: Optional[int] = None,
        frame: Optional[int] = None,
        frames: Optional[Tuple[int, int]] = None,
        width: Optional[int] = None,
        height: Optional[int] = None,
        aa: Optional[int] = None,
        max_depth: Optional[int] = None,
        tile: Optional[int] = None,
        sampler: Optional[str] = None,
        target_error: Optional[float] = None,
        time_limit_ms: Optional[int] = None,
        verify: Optional[str] = None,
        after: Sequence[int] = (),
        chunk_size: int = MAX_CHUNK,
        on_upload: Optional[UploadCallback] = None,
    ) -> Job:
        """Submits a scene with the files it names, and returns the new job.

        ``scene`` is a scene file's path (its files are read beside it, and the job
        is named after it) or a scene as a dict (its files read under ``base_dir``,
        by default the current directory). The files go to the coordinator's store
        as ``tessera submit`` sends them: resolved by the coordinator, uploaded in
        chunks of at most ``chunk_size`` bytes from where the store's upload stands
        (so an upload cut off is resumed), and sent again if the store lost one
        before the job was made. ``frames=(first, last)`` makes a sequence job.
        ``after`` names jobs that must be done before this one starts (``tessera
        submit --after``): it waits until then, and fails, naming the job, if one of
        them fails or is cancelled. The settings are ``tessera submit``'s flags."""
        scene_value: Union[str, Mapping[str, Any]]
        if isinstance(scene, Mapping):
            scene_value = scene
            base = Path(base_dir) if base_dir is not None else Path.cwd()
        else:
            scene_path = Path(scene)
            scene_value = scene_path.read_text(encoding="utf-8")
            base = Path(base_dir) if base_dir is not None else scene_path.parent
            if name is None:
                name = scene_path.stem
        assets = self._send_files(scene_value, base, chunk_size, on_upload)
        body: Dict[str, Any] = {
            "scene": scene_value,
            "name": name,
            "submitter": submitter,
            "priority": priority,
            "frame": frame,
            "frames": None if frames is None else {"first": int(frames[0]), "last": int(frames[1])},
            "width": width,
            "height": height,
            "aa": aa,
            "max_depth": max_depth,
            "tile": tile,
            "sampler": sampler,
            "target_error": target_error,
            "time_limit_ms": time_limit_ms,
            "verify": verify,
            "assets": [a.to_json() for a in assets.values()],
            "after": [int(j) for j in after] or None,
        }
        body = {k: v for k, v in body.items() if v is not None}
        paths = {a.sha256: base / a.name for a in assets.values()}
        for attempt in range(SUBMIT_ATTEMPTS):
            try:
                answer = self._json("POST", "/jobs", body=body)
            except TesseraError as e:
                if e.kind != "lacking" or attempt + 1 == SUBMIT_ATTEMPTS:
                    raise
                # The store lost files since they were sent: send them again.
                for key in self.lacking(e.lacking):
                    self.upload(paths[key.sha256], key, key.received, chunk_size, on_upload=on_upload)
                continue
            return self.job(int(answer["id"]))
        raise AssertionError("unreachable")

    def _send_files(
        self,
        scene: Union[str, Mapping[str, Any]],
        base: Path,
        chunk_size: int,
        on_upload: Optional[UploadCallback],
    ) -> Dict[str, Asset]:
        """Resolves the scene's files, uploading those the store lacks, until the
        coordinator says nothing is missing: the files, by name."""
        given: Dict[str, Asset] = {}
        for _ in range(RESOLVE_ROUNDS):
            resolution = self.resolve(scene, list(given.values()))
            if resolution.complete:
                return {a.name: a for a in resolution.files}
            for missing in resolution.missing:
                path = base / missing
                if not path.is_file():
                    raise TesseraError(
                        f"the scene reads {missing!r}, which is not a file under {base}", "missing_file"
                    )
                key = file_key(path)
                given[missing] = Asset(missing, key.sha256, key.size)
            by_key = {(a.sha256, a.size): a.name for a in given.values()}
            for lacking in resolution.lacking:
                name = by_key[(lacking.sha256, lacking.size)]
                self.upload(
                    base / name, lacking, lacking.received, chunk_size, on_upload=on_upload, name=name
                )
        raise TesseraError(f"the scene's files are still not all stored after {RESOLVE_ROUNDS} rounds", "protocol")

    # ---------------------------------------------------------------- events

    def events(
        self,
        after: Optional[int] = None,
        job: Optional[int] = None,
        kinds: Optional[Iterable[str]] = None,
        follow: bool = True,
        idle_timeout: float = 45.0,
        reconnect_for: float = 60.0,
    ) -> Iterator[StreamEvent]:
        """The farm's events (``GET /api/v1/events``, docs/events.md), as
        :class:`Event` and :class:`GapEvent` objects.

        Without ``after`` it starts with the events from now on; ``after=N``
        resumes after event N (``0``: everything kept). ``job`` and ``kinds``
        filter. With ``follow=False`` it ends once caught up with what the
        coordinator keeps. A stream cut (the connection lost, the coordinator
        restarted, ``idle_timeout`` seconds without even a heartbeat, a
        ``lagged`` end) is resumed with ``Last-Event-ID`` of the last event seen,
        so nothing kept is lost or repeated; failing to reconnect for
        ``reconnect_for`` seconds raises TesseraError ``connection``. Refusals
        (a wrong token, an unknown kind) raise at once.
        """
        query: Dict[str, Any] = {"job": job, "follow": None if follow else False}
        if kinds is not None:
            query["kinds"] = ",".join(kinds)
        last: Optional[int] = after
        failing_since: Optional[float] = None
        delay = 0.1
        while True:
            headers = {"Accept": "text/event-stream"}
            if last is not None:
                headers["Last-Event-ID"] = str(last)
            try:
                conn, response = self._open("GET", "/events", query, headers=headers, timeout=idle_timeout)
            except TesseraError as e:
                if e.kind not in ("connection", "unavailable"):
                    raise
                now = time.monotonic()
                failing_since = failing_since or now
                if now - failing_since > reconnect_for:
                    raise
                time.sleep(delay)
                delay = min(delay * 2, 2.0)
                continue
            failing_since = None
            delay = 0.1
            ended = False
            try:
                for event_id, kind, data in _sse(response):
                    if event_id is None:
                        continue  # not an event of this API
                    last = event_id
                    if kind == "":
                        continue  # only where the stream stands
                    if kind == "lagged":
                        # Fell behind the live events: resume from the database.
                        break
                    yield stream_event(event_id, kind, data)
                else:
                    ended = True
            except (OSError, http.client.HTTPException):
                pass  # cut off: resume below
            finally:
                conn.close()
            if ended and not follow:
                return


def _sse(response: http.client.HTTPResponse) -> Iterator[Tuple[Optional[int], str, JsonObject]]:
    """A server-sent event stream's events: id, kind and JSON data (comments and
    heartbeats skipped), until the stream ends."""
    event_id: Optional[int] = None
    kind = "message"
    data: List[str] = []
    while True:
        raw = response.readline()
        if not raw:
            return
        line = raw.decode("utf-8").rstrip("\r\n")
        if not line:
            if data:
                try:
                    parsed = json.loads("\n".join(data))
                except ValueError as e:
                    raise TesseraError(f"an event's data is not JSON: {data!r}", "protocol") from e
                yield event_id, kind, parsed if isinstance(parsed, dict) else {"value": parsed}
            elif event_id is not None:
                # An id without data: where the stream stands, to resume after.
                yield event_id, "", {}
            event_id, kind, data = None, "message", []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        if value.startswith(" "):
            value = value[1:]
        if name == "id":
            try:
                event_id = int(value)
            except ValueError:
                event_id = None
        elif name == "event":
            kind = value
        elif name == "data":
            data.append(value)


def _refusal(method: str, target: str, status: int, text: bytes) -> TesseraError:
    """The TesseraError of a refused request, from its one line of JSON."""
    try:
        body = json.loads(text)
    except ValueError:
        body = None
    if isinstance(body, dict) and "error" in body:
        return TesseraError(str(body["error"]), str(body.get("kind") or "unknown"), status, body)
    shown = text.decode("utf-8", "replace").strip()[:200] or http.client.responses.get(status, "")
    return TesseraError(f"{method} {target}: {shown}", "protocol", status)


def _write(path: PathLike, data: bytes) -> Path:
    """Writes a file whole: to a temporary file beside it, then renamed."""
    target = Path(path)
    temporary = target.with_name(f".{target.name}.{os.getpid()}.part")
    temporary.write_bytes(data)
    os.replace(temporary, target)
    return target


__all__ = ["Client", "TesseraError", "MAX_CHUNK", "file_key", "normalize_fingerprint"]
