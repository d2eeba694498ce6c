"""Rendering an exported scene: on a farm through the Python client, or on this
machine with the ``tessera`` command. Pure Python (no bpy), so that it can run in a
thread while Blender's UI goes on: Blender's data must not be touched outside its
main thread, so the add-on exports first, then hands this job the files.

A job reports progress through ``progress`` (a fraction in [0, 1], or None when it
cannot tell, and a line of text) and stops early when ``cancel`` is set. Whatever goes
wrong ends as one ``JobError`` whose text is one readable line."""

import os
import re
import shutil
import subprocess
import sys
import threading
import time

#: How often a cancelled local render and a farm job's status are looked at (s).
POLL = 0.2


class JobError(Exception):
    """A render that did not give its image(s): one line saying why."""


class Cancelled(JobError):
    """The render was stopped on request (Esc)."""


class Settings:
    """What a render is asked for: where (farm address or local command) and how
    (sampler, target error); the size, ``aa`` and depth are in the scene file."""

    def __init__(self, address="", token_file="", tls_fingerprint="", tessera_path="tessera",
                 sampler="grid", target_error=0.0, name=None):
        self.address = address.strip()
        self.token_file = os.path.expanduser(token_file.strip()) if token_file else ""
        self.tls_fingerprint = tls_fingerprint.strip()
        self.tessera_path = tessera_path or "tessera"
        self.sampler = sampler
        self.target_error = float(target_error or 0.0)
        self.name = name


def one_line(text):
    """The first meaningful line of a message (tracebacks never reach a report)."""
    lines = [l.strip() for l in str(text).splitlines() if l.strip()]
    return lines[0] if lines else "failed"


class RenderJob:
    """Renders ``scene_path`` (a still, or Tessera frames ``frames=(1, N)``) and writes
    the PNGs into ``out_dir``: ``render.png`` for a still, ``frame_0001.png``... (Tessera's
    frame numbers) for a sequence. ``run()`` returns the list of PNG paths."""

    def __init__(self, settings, scene_path, out_dir, frames=None, mesh_names=None):
        self.settings = settings
        #: {mesh file as the scene names it: [objects using it]}, for error messages.
        self.mesh_names = mesh_names or {}
        self.scene_path = scene_path
        self.out_dir = out_dir
        self.frames = frames
        self.cancel = threading.Event()
        self.fraction = None
        self.status = "exported"
        self.job_id = None
        self._lock = threading.Lock()

    # -- progress, read from Blender's main thread

    def progress(self):
        with self._lock:
            return self.fraction, self.status

    def _say(self, fraction, status):
        with self._lock:
            self.fraction, self.status = fraction, status

    # -- the work

    def run(self):
        os.makedirs(self.out_dir, exist_ok=True)
        try:
            if self.settings.address:
                return self._run_farm()
            return self._run_local()
        except JobError:
            raise
        except Exception as e:  # anything else still ends as one line
            raise JobError(self._name_files(one_line(e))) from e

    def _name_files(self, text):
        """The coordinator names a file by its SHA-256: say which objects' mesh it is."""
        def name(match):
            for file, objects in self.mesh_names.items():
                stem = os.path.splitext(os.path.basename(file))[0]
                if stem and match.group(1).startswith(stem):
                    return "the mesh of %s (%s)" % (", ".join(objects), file)
            return match.group(0)

        return re.sub(r"sha256:([0-9a-f]{64})", name, text)

    def _cancelled(self):
        if self.job_id is not None:
            raise Cancelled("cancelled (job %d cancelled on the farm)" % self.job_id)
        raise Cancelled("cancelled")

    def _run_local(self):
        exe = shutil.which(self.settings.tessera_path) or self.settings.tessera_path
        args = [exe, "render", self.scene_path, "--sampler", self.settings.sampler]
        if self.settings.target_error > 0:
            args += ["--target-error", repr(self.settings.target_error)]
        if self.frames:
            args += ["--frames", "%d-%d" % self.frames, "-o", self.out_dir]
            outputs = [os.path.join(self.out_dir, "frame_%04d.png" % f)
                       for f in range(self.frames[0], self.frames[1] + 1)]
        else:
            out = os.path.join(self.out_dir, "render.png")
            args += ["-o", out]
            outputs = [out]
        self._say(None, "rendering on this machine")
        try:
            proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True)
        except OSError as e:
            raise JobError("cannot run %s: %s (set the tessera command in the Tessera panel)"
                           % (self.settings.tessera_path, e.strerror or e)) from e
        stderr = []
        reader = threading.Thread(target=lambda: stderr.append(proc.stderr.read()), daemon=True)
        reader.start()
        while proc.poll() is None:
            if self.cancel.is_set():
                proc.kill()
                proc.wait()
                self._cancelled()
            if self.frames:
                done = sum(1 for p in outputs if os.path.exists(p))
                self._say(done / len(outputs), "rendering on this machine: %d of %d frames"
                          % (done, len(outputs)))
            time.sleep(POLL)
        reader.join()
        if proc.returncode != 0:
            raise JobError("tessera render: " + one_line("".join(stderr) or "exit status %d"
                                                         % proc.returncode))
        self._say(1.0, "done")
        return outputs

    def _client(self):
        here = os.path.dirname(os.path.abspath(__file__))
        # The zip vendors the client beside the add-on; a checkout has it in clients/python.
        for p in (os.path.join(here, "vendor"), os.path.join(here, "..", "..", "python", "src")):
            if os.path.isdir(os.path.join(p, "tessera_client")) and p not in sys.path:
                sys.path.append(p)
        from tessera_client import Client
        s = self.settings
        if s.token_file and not os.path.isfile(s.token_file):
            raise JobError("the token file %s does not exist" % s.token_file)
        return Client(s.address, token_file=s.token_file or None,
                      tls_fingerprint=s.tls_fingerprint or None, use_env=False)

    def _run_farm(self):
        client = self._client()
        s = self.settings
        self._say(0.0, "sending the scene to %s" % s.address)
        kwargs = {"sampler": s.sampler, "name": s.name}
        if s.target_error > 0:
            kwargs["target_error"] = s.target_error
        if self.frames:
            kwargs["frames"] = self.frames
        job = client.submit(self.scene_path, **kwargs)
        self.job_id = job.id
        if self.cancel.is_set():
            client.cancel(job.id)
            self._cancelled()
        while not job.ended:
            if self.cancel.is_set():
                client.cancel(job.id)
                self._cancelled()
            # Short waits (a second each), so that a cancel is heard at once.
            job = self._wait_briefly(client, job)
        if job.state != "done":
            raise JobError("job %d %s: %s" % (job.id, job.state, job.error or "no image"))
        outputs = []
        if self.frames:
            for k in range(self.frames[0], self.frames[1] + 1):
                path = os.path.join(self.out_dir, "frame_%04d.png" % k)
                client.frame(job.id, k, path)
                outputs.append(path)
        else:
            path = os.path.join(self.out_dir, "render.png")
            client.image(job.id, path)
            outputs.append(path)
        self._say(1.0, "done")
        return outputs

    def _wait_briefly(self, client, job):
        from tessera_client import TesseraError

        def progress(j):
            self._say(*self._describe(j))

        try:
            return client.wait(job.id, progress=progress, timeout=1.0)
        except TesseraError as e:
            if e.kind == "timeout":
                return client.job(job.id)
            raise

    @staticmethod
    def _describe(job):
        if job.state == "waiting":
            return 0.0, "job %d waiting for jobs %s" % (
                job.id, ", ".join(str(j) for j in job.waiting_for))
        if job.frames is not None:
            n = job.frames.last - job.frames.first + 1
            return job.frames.done / n, "job %d: %d of %d frames" % (job.id, job.frames.done, n)
        if job.tiles_total:
            return (job.tiles_done / job.tiles_total,
                    "job %d %s: %d of %d tiles" % (job.id, job.state, job.tiles_done, job.tiles_total))
        return 0.0, "job %d %s" % (job.id, job.state)
