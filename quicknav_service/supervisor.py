"""`quicknav serve`'s workers as supervised child processes.

A job runs in a worker process, never in the API's: a job that runs out of memory (the kernel's
OOM killer sends SIGKILL) or crashes the interpreter takes only its own process down. The
supervisor sees the process end, fails the job it was running with the reason ("killed: out of
memory", or the signal or exit code), and starts a new worker in its place.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from quicknav_service.jobs.models import JobStatus, StoreUnavailable
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.supervisor")

# cgroup v2, then v1: the count of processes the kernel's OOM killer killed in this cgroup
OOM_COUNTERS = (
    (Path("/sys/fs/cgroup/memory.events"), "oom_kill"),
    (Path("/sys/fs/cgroup/memory/memory.oom_control"), "oom_kill"),
)


def oom_kills() -> int | None:
    """The cgroup's OOM-kill count, or None where none is readable."""
    for path, key in OOM_COUNTERS:
        try:
            for line in path.read_text().splitlines():
                name, _, value = line.partition(" ")
                if name == key:
                    return int(value)
        except (OSError, ValueError):
            continue
    return None


def exit_reason(returncode: int, oom_before: int | None, oom_after: int | None) -> str:
    """Why a worker process ended, as a job's failure reason."""
    if returncode < 0:
        sig = -returncode
        try:
            name = signal.Signals(sig).name
        except ValueError:
            name = f"signal {sig}"
        if sig == signal.SIGKILL:
            if oom_before is not None and oom_after is not None and oom_after > oom_before:
                return "killed: out of memory (the kernel's OOM killer sent SIGKILL to the worker)"
            if oom_before is None or oom_after is None:
                return ("killed: the worker process got SIGKILL (what the kernel's OOM killer"
                        " sends; no OOM-kill count was readable to confirm it)")  # fmt: skip
        return f"killed: the worker process got {name}"
    return f"the worker process exited with code {returncode} while running the job"


def settings_env(settings: Settings) -> dict[str, str]:
    """The settings as QUICKNAV_* variables, so a child process builds the same Settings."""
    env = {}
    for name, value in settings.model_dump().items():
        if value is None:
            continue
        text = ("true" if value else "false") if isinstance(value, bool) else str(value)
        env[f"QUICKNAV_{name.upper()}"] = text
    return env


class _Slot:
    def __init__(self, index: int):
        self.index = index
        self.generation = 0
        self.proc: subprocess.Popen | None = None
        self.worker_id = ""
        self.oom_before: int | None = None
        self.started = 0.0
        self.failures = 0  # quick deaths in a row: the restart waits longer each time


class WorkerSupervisor:
    """``count`` worker processes, each restarted when it ends; ``stop()`` ends them."""

    def __init__(self, settings: Settings, store, count: int, poll_s: float = 0.5):
        self.settings = settings
        self.store = store
        self.slots = [_Slot(i) for i in range(count)]
        self.poll_s = poll_s
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="worker-supervisor", daemon=True)
        self.restarts = 0

    def __len__(self) -> int:
        return len(self.slots)

    def start(self) -> WorkerSupervisor:
        for slot in self.slots:
            self._spawn(slot)
        self._thread.start()
        return self

    def _spawn(self, slot: _Slot) -> None:
        slot.generation += 1
        slot.worker_id = f"embedded-{os.getpid()}-{slot.index}-{slot.generation}"
        env = {**os.environ, **settings_env(self.settings)}
        slot.oom_before = oom_kills()
        slot.started = time.monotonic()
        slot.proc = subprocess.Popen(
            [sys.executable, "-m", "quicknav_service.worker_process", "--id", slot.worker_id,
             "--parent", str(os.getpid())], env=env,
        )  # fmt: skip
        log.info("worker %s started (pid %d)", slot.worker_id, slot.proc.pid)

    def _fail_jobs_of(self, worker_id: str, reason: str) -> None:
        """Fail the job(s) the dead worker held: its lease would only bring them back to run the
        same way again."""
        for _ in range(120):  # the store may be down as well: retry for about a minute
            try:
                running, _ = self.store.list(status=JobStatus.running, limit=500)
                for job in running:
                    if job.worker == worker_id:
                        self.store.finish(job.id, worker_id, JobStatus.failed, error=reason)
                        log.error("job %s failed: %s", job.id, reason)
                return
            except StoreUnavailable:
                if self._stopping.wait(0.5):
                    return

    def _watch(self) -> None:
        while not self._stopping.wait(self.poll_s):
            for slot in self.slots:
                if slot.proc is None or slot.proc.poll() is None:
                    continue
                code = slot.proc.returncode
                reason = exit_reason(code, slot.oom_before, oom_kills())
                log.error("worker %s ended: %s", slot.worker_id, reason)
                self._fail_jobs_of(slot.worker_id, reason)
                if self._stopping.is_set():
                    return
                lived = time.monotonic() - slot.started
                slot.failures = slot.failures + 1 if lived < 30 else 0
                wait = min(0.5 * 2 ** max(slot.failures - 1, 0), 30.0)
                if self._stopping.wait(wait):
                    return
                self.restarts += 1
                self._spawn(slot)

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM every worker (each hands its job back after its current unit), then SIGKILL
        those still running after ``timeout`` seconds."""
        self._stopping.set()
        procs = [s.proc for s in self.slots if s.proc is not None and s.proc.poll() is None]
        for proc in procs:
            proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for proc in procs:
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._thread.is_alive():
            self._thread.join(5)
