"""Long-lived child processes of the tests (servers, workers, dashboards) with their output in a file.

A child whose stdout is a pipe that nobody reads blocks in its next write once the pipe holds
64 KiB: a `quicknav serve` that logs each request stops answering after about 1,100 of them
(measured: a /jobs poll loop got its first 5-second ReadTimeout at request 1,160), and the test
then fails far from the cause. A file never fills, and ``output()`` still gives what the process
wrote, for a failing assertion's message.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path


def log_folder() -> Path:
    """The test run's folder for the logs (``QUICKNAV_TEST_CACHE``, removed with the run's cache),
    or the system's temporary folder outside a test run."""
    run = os.environ.get("QUICKNAV_TEST_CACHE")
    return Path(run) / "processes" if run else Path(tempfile.gettempdir()) / "quicknav-test-processes"


class LoggedProcess(subprocess.Popen):
    """``subprocess.Popen`` with stdout and stderr together in a log file (never a pipe)."""

    def __init__(self, args, **kwargs) -> None:
        for taken in ("stdout", "stderr", "text", "universal_newlines"):
            if taken in kwargs:
                raise TypeError(f"LoggedProcess writes the output to a file itself; drop {taken}=")
        folder = log_folder()
        folder.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix="proc-", suffix=".log", dir=folder)
        self.log_path = Path(name)
        try:
            super().__init__(args, stdout=fd, stderr=subprocess.STDOUT, **kwargs)
        finally:
            os.close(fd)  # the child holds its own copy

    def output(self, last: int = 20_000) -> str:
        """The last ``last`` bytes the process wrote so far, as text (all of it once it has ended)."""
        try:
            data = self.log_path.read_bytes()
        except OSError as e:
            return f"(the output in {self.log_path} cannot be read: {e})"
        return data[-last:].decode(errors="replace") if self.poll() is None else data.decode(errors="replace")

    def finish(self, timeout: float) -> str:
        """Wait for the process to end (it was sent its signal); its whole output."""
        self.wait(timeout)
        return self.output()
