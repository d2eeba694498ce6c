"""The Python client against a real farm (conftest.py): submitting scenes with their
meshes, waiting, images and frames byte for byte `tessera render`'s, every control,
the event stream, refusals, a resumed upload, and TLS pinned to the fingerprint."""

from __future__ import annotations

import json
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, TypeVar

import pytest

from conftest import SCENES, TOKEN, CutProxy, Farm
from tessera_client import (
    MAX_CHUNK,
    Asset,
    Cancelled,
    Client,
    Event,
    FileKey,
    GapEvent,
    Job,
    StreamEvent,
    TesseraError,
    UploadProgress,
    file_key,
)

SMALL: Dict[str, Any] = {"width": 96, "height": 64, "aa": 1}
SMALL_ARGS = ("--width", "96", "--height", "64", "--aa", "1")
T = TypeVar("T")


def collect(items: Iterator[T], until: Optional[Callable[[T], bool]] = None, timeout: float = 60.0) -> List[T]:
    """Items of `items` up to the first for which `until` holds (included), or to
    their end without `until`, read in a thread so that a stream that never brings
    it fails the test instead of hanging it."""
    got: List[T] = []
    failure: List[BaseException] = []
    found = threading.Event()

    def read() -> None:
        try:
            for item in items:
                got.append(item)
                if until is not None and until(item):
                    found.set()
                    return
            if until is None:
                found.set()
        except BaseException as e:  # noqa: BLE001 - reported below
            failure.append(e)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    if failure:
        raise failure[0]
    assert found.is_set(), f"not found within {timeout} s; got {got!r}"
    return got


def is_job_event(kind: str, job: int) -> Callable[[StreamEvent], bool]:
    return lambda e: isinstance(e, Event) and e.kind == kind and e.job is not None and e.job.id == job


def test_a_mesh_scene_submitted_waited_for_with_progress_gives_tessera_renders_image(
    farm: Farm, tmp_path: Path
) -> None:
    client = farm.client()
    seen: List[Job] = []
    job = client.submit(SCENES / "instances.json", submitter="pytest", **SMALL)
    assert (job.name, job.submitter, job.width, job.height, job.aa) == ("instances", "pytest", 96, 64, 1)
    assert job.state in ("queued", "running"), job
    done = client.wait(job.id, progress=seen.append, timeout=120)
    assert done.state == "done", done.error
    assert done.asset_files == 1 and done.asset_bytes == (SCENES / "models/knot.obj").stat().st_size
    # Progress: the status at once, then as tiles are done, ending with the end.
    assert len(seen) >= 2, seen
    assert seen[-1].state == "done" and seen[-1].tiles_done == seen[-1].tiles_total
    assert [j.tiles_done for j in seen] == sorted(j.tiles_done for j in seen)

    reference = farm.render(SCENES / "instances.json", tmp_path / "reference.png", *SMALL_ARGS)
    assert client.image_bytes(job.id) == reference
    written = client.image(job.id, tmp_path / "fetched.png")
    assert written.read_bytes() == reference

    log = list(client.job_events(job.id))
    assert log, "a job's log has entries"
    assert [e.seq for e in log] == sorted({e.seq for e in log})
    assert any(job.id == j.id for j in client.jobs(submitter="pytest"))


def test_a_sequence_jobs_frames_are_tessera_renders_frames(farm: Farm, tmp_path: Path) -> None:
    client = farm.client()
    scene = SCENES / "seed-orbit.json"
    args = ("--width", "48", "--height", "32", "--aa", "1")
    job = client.submit(scene, frames=(3, 4), width=48, height=32, aa=1)
    done = client.wait(job.id, timeout=120)
    assert done.state == "done", done.error
    assert done.frames is not None and (done.frames.first, done.frames.last, done.frames.done) == (3, 4, 2)
    for k in (3, 4):
        reference = farm.render(scene, tmp_path / f"reference_{k}.png", "--frame", str(k), *args)
        path = client.frame(job.id, k, tmp_path / f"frame_{k:04}.png")
        assert path.read_bytes() == reference, f"frame {k}"
    with pytest.raises(TesseraError) as refused:
        client.frame_bytes(job.id, 9)
    assert refused.value.status is not None and 400 <= refused.value.status < 500


def test_every_control_of_a_job(farm: Farm) -> None:
    client = farm.client()
    # No worker takes tiles meanwhile: the job stays queued for the controls.
    for name in farm.workers:
        client.disable_worker(name)
    try:
        assert all(w.disabled for w in client.workers() if w.name in farm.workers)
        job = client.submit(SCENES / "seed.json", name="controls", width=64, height=48, aa=1)
        assert job.state == "queued"
        assert client.priority(job.id, 5).priority == 5
        paused = client.pause(job.id)
        assert (paused.state, paused.paused) == ("paused", True)
        assert [j.id for j in client.jobs(state="paused", name="controls")] == [job.id]
        assert client.resume(job.id).state == "queued"
        queued = client.requeue(job.id, [0])
        assert queued.state == "queued"
        assert client.cancel(job.id) == Cancelled(job.id, already_cancelled=False)
        assert client.cancel(job.id).already_cancelled
        with pytest.raises(TesseraError) as refused:
            client.pause(job.id)
        assert (refused.value.kind, refused.value.status) == ("state", 409)
        assert client.job(job.id).state == "cancelled"
        assert client.retry(job.id).state == "queued"
    finally:
        for name in farm.workers:
            client.enable_worker(name)
    assert not any(w.disabled for w in client.workers())
    done = client.wait(job.id, timeout=60)
    assert done.state == "done", done.error
    with pytest.raises(TesseraError) as refused:
        client.requeue(job.id, [0])
    assert refused.value.kind == "state"

    with pytest.raises(TesseraError) as grid:
        client.refine(job.id, target_error=2.0)
    assert (grid.value.kind, grid.value.status) == ("invalid", 422)
    adaptive = client.submit(SCENES / "seed.json", width=64, height=48, aa=4, target_error=8.0)
    assert adaptive.sampler == "adaptive" and adaptive.target_error == 8.0
    assert client.wait(adaptive.id, timeout=60).state == "done"
    refined = client.refine(adaptive.id, target_error=2.0)
    assert refined.id != adaptive.id and (refined.sampler, refined.target_error) == ("adaptive", 2.0)
    assert client.wait(refined.id, timeout=60).state == "done"
    kinds = [e.event for e in client.job_events(job.id)]
    for kind in ("priority", "paused", "resumed", "requeued", "retried"):
        assert kind in kinds, (kind, kinds)

    for ended in (refined.id, adaptive.id, job.id):
        client.delete(ended)
    with pytest.raises(TesseraError) as gone:
        client.job(job.id)
    assert (gone.value.kind, gone.value.status) == ("not_found", 404)


def test_a_job_submitted_after_others_waits_fails_with_them_and_goes_on_when_retried(
    farm: Farm,
) -> None:
    client = farm.client()
    for name in farm.workers:
        client.disable_worker(name)
    try:
        first = client.submit(SCENES / "seed.json", name="first", width=64, height=48, aa=1)
        second = client.submit(SCENES / "seed.json", name="second", after=[first.id], **SMALL)
        assert (second.state, second.after, second.waiting_for) == ("waiting", (first.id,), (first.id,))
        assert [j.id for j in client.jobs(state="waiting", name="second")] == [second.id]
        with pytest.raises(TesseraError) as missing:
            client.submit(SCENES / "seed.json", after=[10**9], **SMALL)
        assert (missing.value.kind, missing.value.status) == ("not_found", 404)
        client.cancel(first.id)
        failed = client.wait(second.id, timeout=30)
        assert failed.state == "failed"
        assert failed.error == f"job {first.id}, which this job waits for, is cancelled"
        # The dependent first: refused, naming the job to retry first.
        with pytest.raises(TesseraError) as early:
            client.retry(second.id)
        assert early.value.kind == "state" and f"retry job {first.id} first" in early.value.message
        assert client.retry(first.id).state == "queued"
        assert client.retry(second.id).state == "waiting"
        with pytest.raises(TesseraError) as needed:
            client.delete(first.id)
        assert needed.value.kind == "state"
    finally:
        for name in farm.workers:
            client.enable_worker(name)
    done = client.wait(second.id, timeout=60)
    assert done.state == "done", done.error
    assert done.waiting_for == ()
    kinds = [e.event for e in client.job_events(second.id)]
    assert "waiting" in kinds and "released" in kinds, kinds
    for ended in (second.id, first.id):
        client.delete(ended)


def test_a_worker_drained_finishes_and_leaves(farm: Farm) -> None:
    client = farm.client()
    process = farm.start_worker("w-drain")
    farm.wait_for_workers(["w-drain"])
    acted = client.drain_worker("w-drain")
    # Listed draining, unless it has already finished and left by the answer.
    assert [(w.name, w.draining) for w in acted] in ([("w-drain", True)], [])
    assert process.wait(timeout=30) == 0
    deadline = time.monotonic() + 10
    while "w-drain" in {w.name for w in client.workers()}:
        assert time.monotonic() < deadline, "the drained worker is still listed"
        time.sleep(0.05)
    with pytest.raises(TesseraError) as refused:
        client.drain_worker("no-such-worker")
    assert refused.value.kind == "not_found"


def test_events_replayed_filtered_followed_and_resumed_by_id(farm: Farm) -> None:
    client = farm.client()
    kept = collect(client.events(after=0, follow=False))
    assert kept and all(isinstance(e, Event) for e in kept)
    assert [e.id for e in kept] == sorted({e.id for e in kept})
    joined = [e for e in kept if isinstance(e, Event) and e.kind == "joined"]
    assert {"w1", "w2"} <= {str((e.worker or {}).get("name")) for e in joined}

    stream = client.events(after=kept[-1].id, kinds=["submitted", "started", "done"])
    job = client.submit(SCENES / "seed.json", name="followed", width=32, height=24, aa=1)
    got = collect(stream, is_job_event("done", job.id))
    mine = [e for e in got if isinstance(e, Event) and e.job is not None and e.job.id == job.id]
    assert [e.kind for e in mine] == ["submitted", "started", "done"]
    assert isinstance(mine[0], Event) and mine[0].job is not None and mine[0].job.name == "followed"
    assert all(e.unix_ms > 1_600_000_000_000 for e in mine if isinstance(e, Event))

    # Resumed after the submission, only this job's: the rest of its events.
    resumed = collect(client.events(after=mine[0].id, job=job.id, follow=False))
    assert [e.kind for e in resumed] == ["started", "done"]
    assert [e.id for e in resumed] == [e.id for e in mine[1:]]
    only_done = collect(client.events(after=0, kinds=["done"], follow=False))
    assert job.id in {e.job.id for e in only_done if isinstance(e, Event) and e.job}
    assert {e.kind for e in only_done} == {"done"}


def test_a_stream_cut_midway_resumes_with_last_event_id_losing_nothing(farm: Farm) -> None:
    direct = farm.client()
    proxy = CutProxy(farm.http)
    try:
        relayed = farm.client(url=f"http://{proxy.addr}")
        start = collect(direct.events(after=0, follow=False))[-1].id
        stream = relayed.events(after=start)
        first = direct.submit(SCENES / "seed.json", name="before-cut", width=32, height=24, aa=1)
        got = collect(stream, is_job_event("submitted", first.id))
        proxy.cut()
        # Meanwhile the job runs, and another is submitted and runs.
        assert direct.wait(first.id, timeout=60).state == "done"
        second = direct.submit(SCENES / "seed.json", name="after-cut", width=32, height=24, aa=1)
        assert direct.wait(second.id, timeout=60).state == "done"
        got += collect(stream, is_job_event("done", second.id))
        assert proxy.accepted >= 2, "the stream reconnected"
        kept = collect(direct.events(after=start, follow=False))
        kept = kept[: [e.id for e in kept].index(got[-1].id) + 1]
        assert [(e.id, e.kind) for e in got] == [(e.id, e.kind) for e in kept]
    finally:
        proxy.close()


def test_refusals_carry_their_kind_and_status(farm: Farm, tmp_path: Path) -> None:
    with pytest.raises(TesseraError) as wrong:
        list(farm.client(token="not-the-token").jobs())
    assert (wrong.value.kind, wrong.value.status) == ("forbidden", 403), wrong.value
    with pytest.raises(TesseraError) as none:
        farm.client(token=None).workers()
    assert (none.value.kind, none.value.status) == ("unauthorized", 401), none.value
    with pytest.raises(TesseraError) as wrong_stream:
        next(farm.client(token="not-the-token").events(after=0, follow=False))
    assert wrong_stream.value.kind == "forbidden"

    client = farm.client()
    with pytest.raises(TesseraError) as missing:
        client.job(987654)
    assert (missing.value.kind, missing.value.status) == ("not_found", 404)
    assert missing.value.message and "987654" in missing.value.message
    with pytest.raises(TesseraError) as bad:
        list(client.jobs(state="sleeping"))
    assert (bad.value.kind, bad.value.status) == ("invalid", 400)
    with pytest.raises(TesseraError) as unknown_kind:
        collect(client.events(kinds=["nonsense"], follow=False))
    assert (unknown_kind.value.kind, unknown_kind.value.status) == ("invalid", 400)
    with pytest.raises(TesseraError) as image:
        client.image_bytes(987654)
    assert image.value.kind == "not_found"

    # A scene naming a file that is not there: said before anything is submitted.
    scene = json.loads((SCENES / "instances.json").read_text())
    scene["objects"][1]["file"] = "models/absent.obj"
    with pytest.raises(TesseraError) as absent:
        client.submit(scene, base_dir=tmp_path, **SMALL)
    assert absent.value.kind == "missing_file" and "models/absent.obj" in absent.value.message
    with pytest.raises(TesseraError) as invalid:
        client.submit({"objects": "not a list"}, **SMALL)
    assert invalid.value.kind == "invalid" and invalid.value.status in (400, 422), invalid.value
    with pytest.raises(ValueError):
        client.upload(SCENES / "models/knot.obj", chunk_size=MAX_CHUNK + 1)

    # Nobody listening: a connection error, not a hang.
    with pytest.raises(TesseraError) as unreachable:
        Client("http://127.0.0.1:9", token=TOKEN, use_env=False, timeout=5).workers()
    assert unreachable.value.kind == "connection" and unreachable.value.status is None


def test_an_upload_cut_off_is_resumed_by_another_client_where_the_store_stands(
    farm: Farm, tmp_path: Path
) -> None:
    scene_file = fresh_mesh_scene(tmp_path)
    mesh = tmp_path / "models" / "fresh.obj"
    key = file_key(mesh)
    chunk = 64 * 1024

    first = farm.client()
    assert first.lacking([key]) == [FileKey(key.sha256, key.size, 0)]
    assert first.upload(mesh, chunk_size=chunk, max_chunks=1) == chunk
    assert first.lacking([key]) == [FileKey(key.sha256, key.size, chunk)]

    # Another client (another process, say) submits the scene: the upload goes on
    # from the store's received bytes, in chunks of the size asked.
    uploads: List[UploadProgress] = []
    job = farm.client().submit(scene_file, chunk_size=chunk, on_upload=uploads.append, **SMALL)
    assert uploads and uploads[0].offset == chunk, uploads
    assert uploads[0].name == "models/fresh.obj"
    assert all(0 < u.received - u.offset <= chunk for u in uploads), uploads
    assert [u.offset for u in uploads[1:]] == [u.received for u in uploads[:-1]]
    assert uploads[-1].complete and uploads[-1].received == key.size
    assert first.lacking([key]) == []

    done = first.wait(job.id, timeout=120)
    assert done.state == "done", done.error
    reference = farm.render(scene_file, tmp_path / "reference.png", *SMALL_ARGS)
    assert first.image_bytes(job.id) == reference

    # Submitted again: nothing to upload.
    again: List[UploadProgress] = []
    repeat = first.submit(scene_file, on_upload=again.append, **SMALL)
    assert again == []
    first.cancel(repeat.id)


def fresh_mesh_scene(directory: Path) -> Path:
    """The instances scene with a mesh new to the store (the knot, with a comment
    line of its own), written in `directory`: the scene's path."""
    (directory / "models").mkdir(exist_ok=True)
    mesh = directory / "models" / "fresh.obj"
    mesh.write_bytes(f"# {uuid.uuid4()}\n".encode() + (SCENES / "models/knot.obj").read_bytes())
    scene = json.loads((SCENES / "instances.json").read_text())
    for thing in scene["objects"]:
        if thing.get("type") == "mesh":
            thing["file"] = "models/fresh.obj"
    scene_file = directory / "fresh.json"
    scene_file.write_text(json.dumps(scene))
    return scene_file


def test_a_submission_refused_for_a_lacking_file_uploads_it_and_is_sent_again(
    farm: Farm, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    scene_file = fresh_mesh_scene(tmp_path)
    mesh = tmp_path / "models" / "fresh.obj"
    key = file_key(mesh)
    client = farm.client()
    # As if the store had lost the file after it was resolved and uploaded: the
    # submission names a file the store does not have, and the coordinator says so.
    monkeypatch.setattr(
        client, "_send_files", lambda *_: {"models/fresh.obj": Asset("models/fresh.obj", key.sha256, key.size)}
    )
    with pytest.raises(TesseraError) as lacking:
        client._json("POST", "/jobs", body={"scene": scene_file.read_text(), "assets": [
            {"name": "models/fresh.obj", "sha256": key.sha256, "size": key.size}]})
    assert (lacking.value.kind, lacking.value.status) == ("lacking", 409)
    assert lacking.value.lacking == [FileKey(key.sha256, key.size)]
    uploads: List[UploadProgress] = []
    job = client.submit(scene_file, on_upload=uploads.append, **SMALL)
    assert uploads and uploads[-1].complete and uploads[0].offset == 0, uploads
    assert client.lacking([key]) == []
    done = client.wait(job.id, timeout=120)
    assert done.state == "done" and done.asset_files == 1, done


def test_tls_pinned_to_the_fingerprint_and_a_wrong_pin_refused(tls_farm: Farm) -> None:
    fingerprint = tls_farm.fingerprint
    assert fingerprint is not None and len(fingerprint) == 64
    client = tls_farm.client()
    assert client.url.startswith("https://")
    assert client.workers() == []
    # The openssl form of the same pin, and an address without a scheme: HTTPS.
    openssl_form = ":".join(fingerprint.upper()[i : i + 2] for i in range(0, 64, 2))
    assert tls_farm.client(url=tls_farm.http, tls_fingerprint=openssl_form).workers() == []

    other = "ab" * 32
    with pytest.raises(TesseraError) as refused:
        tls_farm.client(tls_fingerprint=other).workers()
    message = str(refused.value)
    assert refused.value.kind == "tls" and refused.value.status is None
    assert fingerprint in message and other in message, message
    with pytest.raises(TesseraError) as stream_refused:
        next(tls_farm.client(tls_fingerprint=other).events(after=0, follow=False))
    assert stream_refused.value.kind == "tls"
    # Without a pin, the self-signed certificate is not trusted.
    with pytest.raises(TesseraError) as untrusted:
        tls_farm.client(tls_fingerprint=None).workers()
    assert untrusted.value.kind == "tls", untrusted.value
    with pytest.raises(ValueError):
        tls_farm.client(tls_fingerprint="12ab")
    with pytest.raises(ValueError):
        tls_farm.client(url=f"http://{tls_farm.http}")


def test_a_stream_resuming_after_trimmed_events_gets_a_gap_first(tls_farm: Farm) -> None:
    client = tls_farm.client()
    ids = [client.submit(SCENES / "seed.json", width=16, height=16, aa=1).id for _ in range(5)]
    deadline = time.monotonic() + 10
    while True:
        kept = collect(client.events(after=0, follow=False))
        events = [e for e in kept if isinstance(e, Event)]
        if events and events[-1].job is not None and events[-1].job.id == ids[-1]:
            break
        assert time.monotonic() < deadline, kept
        time.sleep(0.05)
    gap = kept[0]
    assert isinstance(gap, GapEvent), kept
    assert (gap.kind, gap.after, gap.oldest_kept, gap.id) == ("gap", 0, kept[1].id, kept[1].id - 1)
    assert "no longer kept" in gap.message and gap.job is None and gap.worker is None
    assert [e.kind for e in kept[1:]] == ["submitted"] * 3
    assert [e.job.id for e in events if e.job] == ids[-3:]
    # Resuming right after the gap is not told of it again.
    assert [e.id for e in collect(client.events(after=gap.id, follow=False))] == [e.id for e in kept[1:]]
    for job in ids:
        client.cancel(job)


def test_the_environment_gives_what_the_arguments_do_not(
    tls_farm: Farm, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert tls_farm.fingerprint is not None
    monkeypatch.setenv("TESSERA_URL", tls_farm.url)
    monkeypatch.setenv("TESSERA_TOKEN_FILE", str(tls_farm.token_file))
    monkeypatch.delenv("TESSERA_TOKEN", raising=False)
    monkeypatch.setenv("TESSERA_TLS_FINGERPRINT", tls_farm.fingerprint)
    assert Client().workers() == []
    monkeypatch.setenv("TESSERA_TLS_FINGERPRINT", "")
    with pytest.raises(TesseraError) as untrusted:
        Client().workers()
    assert untrusted.value.kind == "tls"
