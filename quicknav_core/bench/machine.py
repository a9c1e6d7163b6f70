"""Where a benchmark ran: figures are only comparable on the same machine, so every report names it."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

import numpy as np


def machine_info() -> dict[str, Any]:
    """CPU model, cores, memory, JAX backend and devices, versions."""
    import jax
    import jaxlib

    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gib = None
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
        mem_gib = round(pages * size / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    devices = jax.devices()
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": mem_gib,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in devices],
        "device_kind": devices[0].device_kind if devices else "",
    }


def machine_line() -> str:
    """The machine in words (CPU, cores, backend), as reports list it beside each figure."""
    info = machine_info()
    return f"{info['cpu']}, {info['cores']} cores, {info['jax_backend']}"


def cpu_probe() -> dict[str, float]:
    """Seconds a fixed single-threaded piece of work takes here (hash 256 MB with SHA-256, sort 4
    million floats, each the best of three): a VM's speed moves 15-25 % between runs of the same
    code, so a figure measured beside this probe can be compared with one from another run or
    machine (``.ci/run`` prints it before the tests)."""
    import hashlib
    import time

    block = np.random.default_rng(0).bytes(1 << 24)  # 16 MB
    values = np.random.default_rng(1).random(1 << 22)

    def best(fn) -> float:
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return round(min(times), 3)

    def hash_256mb() -> None:
        h = hashlib.sha256()
        for _ in range(16):
            h.update(block)

    return {"sha256_256mb_s": best(hash_256mb), "sort_4m_floats_s": best(lambda: np.sort(values))}


if __name__ == "__main__":  # python -m quicknav_core.bench.machine
    probe = cpu_probe()
    print(f"machine: {machine_line()}; cpu probe: SHA-256 of 256 MB {probe['sha256_256mb_s']} s,"
          f" sort of 4M floats {probe['sort_4m_floats_s']} s", flush=True)
