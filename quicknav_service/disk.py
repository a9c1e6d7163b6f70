"""Whether the data folder takes writes: the one check behind ``/readyz``'s ``disk``, a queued job's
``waiting`` reason, and a worker's announcement (a worker whose disk is full claims nothing)."""

from __future__ import annotations

import errno
import os
import threading
import time
from pathlib import Path

PROBE_BYTES = 64 * 1024
# an open route must not be a way to make the server write: a good disk is probed at most this often
DISK_PROBE_EVERY_S = 5.0
# below this many free bytes (statvfs, which writes nothing) a cached "ok" is not trusted
DISK_LOW_BYTES = 4 * PROBE_BYTES
_disk_probes: dict[Path, float] = {}  # when each folder last took a probe
_disk_lock = threading.Lock()


def disk_check(data_dir: Path) -> str:
    """'ok' if a small file could be written and synced in the data folder, else why not.

    Only a good answer is reused, for DISK_PROBE_EVERY_S seconds and only while the file system
    still reports free space; a failing probe writes nothing that lasts, so a full or unwritable
    disk is probed again on the next call and its recovery is seen at once."""
    with _disk_lock:
        last_ok = _disk_probes.get(data_dir)
        if last_ok is not None and time.monotonic() - last_ok < DISK_PROBE_EVERY_S \
                and _free_bytes(data_dir) >= DISK_LOW_BYTES:  # fmt: skip
            return "ok"
        result = _probe_disk(data_dir)
        if result == "ok":
            _disk_probes[data_dir] = time.monotonic()
        else:
            _disk_probes.pop(data_dir, None)
        return result


def _free_bytes(data_dir: Path) -> int:
    try:
        st = os.statvfs(data_dir)
    except OSError:
        return 0
    return st.f_bavail * st.f_frsize


def _probe_disk(data_dir: Path) -> str:
    probe = data_dir / f".ready-probe-{os.getpid()}"
    try:
        with open(probe, "wb") as f:
            f.write(b"\0" * PROBE_BYTES)
            f.flush()
            os.fsync(f.fileno())
        return "ok"
    except OSError as e:
        return "full" if e.errno == errno.ENOSPC else "not writable"
    finally:
        probe.unlink(missing_ok=True)



def disk_full(data_dir: Path) -> bool:
    """Whether the data folder's disk is full (the probe failed with ENOSPC)."""
    return disk_check(data_dir) == "full"
