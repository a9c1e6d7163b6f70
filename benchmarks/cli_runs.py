"""Benchmarks that run `quicknav` commands as a user does: each in a fresh process, timed, and a
run folder that already holds a finished training reused."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(cmd: list[str]) -> float:
    """Run a quicknav command in a fresh process; its wall time in seconds."""
    start = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def trained(run_dir: Path, preset: str) -> bool:
    """Whether ``run_dir`` holds a training of ``preset`` that reached its step budget."""
    from quicknav_core.config import get_preset

    metrics = run_dir / "metrics.jsonl"
    if not metrics.exists():
        return False
    lines = [json.loads(x) for x in metrics.read_text().splitlines() if x.strip()]
    return bool(lines) and lines[-1].get("env_steps", 0) >= get_preset(preset).total_steps
