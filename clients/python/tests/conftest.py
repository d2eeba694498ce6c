"""A real farm for the client's tests: `tessera coordinator` with a client token and
HTTP, and real `tessera worker`s, all on 127.0.0.1 in temporary directories, killed
at the end. The binary is `TESSERA_BIN`, or `tessera` on PATH."""

from __future__ import annotations

import os
import queue
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any, Dict, Iterator, List, Optional, Sequence

import pytest

from tessera_client import Client

REPO = Path(__file__).resolve().parents[3]
SCENES = REPO / "scenes"
TOKEN = "3c9d0f6e2b8a41d7a5e1c0b9f4d28e7a"
#: How long a daemon has to print its addresses, a worker to join.
START_TIMEOUT = 20.0


def tessera_bin() -> str:
    found = os.environ.get("TESSERA_BIN") or shutil.which("tessera")
    if not found or not os.access(found, os.X_OK):
        pytest.fail(
            "no tessera binary: set TESSERA_BIN to it (cargo build --release --bin tessera: "
            "target/release/tessera) or put tessera on PATH",
            pytrace=False,
        )
    # The daemons run in directories of their own: a relative path is made absolute.
    return os.path.abspath(found)


class Farm:
    """A coordinator (and workers) of the tests, killed by :meth:`stop`."""

    def __init__(self, binary: str, directory: Path, extra: Sequence[str] = (), tls: bool = False) -> None:
        self.binary = binary
        self.dir = directory
        self.tls = tls
        self.token_file = directory / "client.token"
        self.token_file.write_text(TOKEN + "\n")
        self.token_file.chmod(0o600)
        self.processes: List[subprocess.Popen[bytes]] = []
        self.workers: List[str] = []
        args = [
            binary, "coordinator", "--data", str(directory / "data"),
            "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
            "--client-token-file", str(self.token_file),
        ]
        if tls:
            args.append("--tls-auto")
        args.extend(extra)
        log = open(directory / "coordinator.log", "wb")
        process = subprocess.Popen(args, cwd=directory, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log)
        self.processes.append(process)
        assert process.stdout is not None
        lines = _lines(process.stdout)
        wanted = 3 if tls else 2
        said: List[str] = []
        deadline = time.monotonic() + START_TIMEOUT
        while len(said) < wanted:
            try:
                said.append(lines.get(timeout=max(0.1, deadline - time.monotonic())))
            except queue.Empty:
                self.stop()
                raise RuntimeError(
                    f"the coordinator did not start: it printed {said!r}; its log:\n"
                    + (directory / "coordinator.log").read_text(errors="replace")[-3000:]
                )
        self.addr = _after(said[0], "listening on ")
        self.http = _after(said[1], "http on ")
        self.fingerprint: Optional[str] = _after(said[2], "tls fingerprint ") if tls else None
        self.url = f"{'https' if tls else 'http'}://{self.http}"

    def client(self, **kwargs: object) -> Client:
        """A client with the farm's token (and pin), reading no environment."""
        settings: Dict[str, Any] = {"token": TOKEN, "tls_fingerprint": self.fingerprint, "use_env": False, "timeout": 30.0}
        settings.update(kwargs)
        url = settings.pop("url", self.url)
        return Client(str(url), **settings)

    def start_worker(self, name: str) -> subprocess.Popen[bytes]:
        args = [self.binary, "worker", "--coordinator", self.addr, "--threads", "1", "--name", name]
        if self.fingerprint:
            args += ["--tls-fingerprint", self.fingerprint]
        log = open(self.dir / f"worker-{name}.log", "wb")
        process = subprocess.Popen(args, cwd=self.dir, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log)
        self.processes.append(process)
        return process

    def wait_for_workers(self, names: Sequence[str]) -> None:
        client = self.client()
        deadline = time.monotonic() + START_TIMEOUT
        while not set(names) <= {w.name for w in client.workers()}:
            assert time.monotonic() < deadline, f"workers {names} did not join"
            time.sleep(0.05)

    def render(self, scene: Path, out: Path, *args: str) -> bytes:
        """`tessera render SCENE -o OUT ARGS`: the reference image's bytes."""
        run = subprocess.run(
            [self.binary, "render", str(scene), "-o", str(out), *args],
            cwd=self.dir, capture_output=True, timeout=120,
        )
        assert run.returncode == 0, run.stderr.decode(errors="replace")
        return out.read_bytes()

    def stop(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.kill()
            process.wait()


def _lines(stream: IO[bytes]) -> "queue.Queue[str]":
    """A daemon's stdout, line by line, read in the background (and drained)."""
    lines: "queue.Queue[str]" = queue.Queue()

    def read() -> None:
        for raw in stream:
            lines.put(raw.decode(errors="replace").strip())

    threading.Thread(target=read, daemon=True).start()
    return lines


def _after(line: str, prefix: str) -> str:
    assert line.startswith(prefix), f"expected {prefix!r}…, got {line!r}"
    return line[len(prefix):].strip()


@pytest.fixture(scope="session")
def farm() -> Iterator[Farm]:
    """The farm most tests share: a coordinator and two workers, w1 and w2."""
    binary = tessera_bin()
    with tempfile.TemporaryDirectory(prefix="tessera-py-") as d:
        farm = Farm(binary, Path(d))
        try:
            for name in ("w1", "w2"):
                farm.start_worker(name)
                farm.workers.append(name)
            farm.wait_for_workers(farm.workers)
            yield farm
        finally:
            farm.stop()


@pytest.fixture(scope="session")
def tls_farm() -> Iterator[Farm]:
    """A coordinator with `--tls-auto` that keeps only 3 events, and no worker."""
    binary = tessera_bin()
    with tempfile.TemporaryDirectory(prefix="tessera-py-tls-") as d:
        farm = Farm(binary, Path(d), ["--event-retention-count", "3"], tls=True)
        try:
            yield farm
        finally:
            farm.stop()


class CutProxy:
    """A TCP relay to an address whose connections the test can cut at once: a
    connection lost midway, as a network or a proxy loses it."""

    def __init__(self, target: str) -> None:
        host, port = target.rsplit(":", 1)
        self.target = (host, int(port))
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.addr = f"127.0.0.1:{self.listener.getsockname()[1]}"
        self.accepted = 0
        self._open: List[socket.socket] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(self.target)
            with self._lock:
                self.accepted += 1
                self._open += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(source: socket.socket, sink: socket.socket) -> None:
        try:
            while True:
                data = source.recv(65536)
                if not data:
                    break
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for s in (source, sink):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def cut(self) -> None:
        """Cuts every connection open now (the relay accepts new ones)."""
        with self._lock:
            for s in self._open:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
            self._open.clear()

    def close(self) -> None:
        self.listener.close()
        self.cut()
