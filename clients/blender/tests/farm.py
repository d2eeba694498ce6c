"""A local farm for the Blender tests and benchmarks: a coordinator with a client
token and HTTP, and workers, on 127.0.0.1, killed by ``stop``. The binary is
$TESSERA, or ``tessera`` on PATH."""

import os
import queue
import shutil
import subprocess
import sys
import threading
import time

TOKEN = "5be1c0d2a9f34e7b8c6d0e1f2a3b4c5d"
START_TIMEOUT = 20.0


def tessera_bin():
    found = os.environ.get("TESSERA") or shutil.which("tessera")
    if not found:
        print("no tessera on PATH (or $TESSERA)")
        sys.exit(2)
    return os.path.abspath(found)


class Farm:
    """A coordinator with a client token and HTTP, and `workers` workers, on 127.0.0.1."""

    def __init__(self, tessera, directory, extra=(), tls=False, workers=1, threads=1):
        self.dir = directory
        os.makedirs(directory, exist_ok=True)
        self.token_file = os.path.join(directory, "client.token")
        with open(self.token_file, "w") as f:
            f.write(TOKEN + "\n")
        os.chmod(self.token_file, 0o600)
        self.processes = []
        log = open(os.path.join(directory, "coordinator.log"), "wb")
        coordinator = subprocess.Popen(
            [tessera, "coordinator", "--data", os.path.join(directory, "data"),
             "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
             "--client-token-file", self.token_file, *(["--tls-auto"] if tls else []), *extra],
            cwd=directory, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log)
        self.processes.append(coordinator)
        lines = queue.Queue()
        threading.Thread(target=lambda: [lines.put(l.decode().strip()) for l in coordinator.stdout],
                         daemon=True).start()
        said = []
        deadline = time.monotonic() + START_TIMEOUT
        while len(said) < (3 if tls else 2):
            try:
                said.append(lines.get(timeout=max(0.1, deadline - time.monotonic())))
            except queue.Empty:
                self.stop()
                raise AssertionError("the coordinator did not start: %r" % said)
        self.addr = said[0].split("listening on ", 1)[1]
        self.url = ("https://" if tls else "http://") + said[1].split("http on ", 1)[1]
        self.fingerprint = said[2].split("tls fingerprint ", 1)[1] if tls else ""
        for k in range(1, workers + 1):
            wlog = open(os.path.join(directory, "worker-%d.log" % k), "wb")
            self.processes.append(subprocess.Popen(
                [tessera, "worker", "--coordinator", self.addr, "--threads", str(threads),
                 "--name", "w%d" % k, *(["--tls-fingerprint", self.fingerprint] if tls else [])],
                cwd=directory, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=wlog))

    def stop(self):
        for p in self.processes:
            if p.poll() is None:
                p.kill()
            p.wait()
