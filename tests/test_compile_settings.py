"""The test run's compile settings (``tests/compile_settings.py``): the test processes compile
quickly, and a process started ``as_a_user_runs()`` (the trainings to a target, admission's measured
processes, README's journeys) compiles as a user's machine does; its JAX sees neither setting."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from jax._src import compiler

from tests.compile_settings import QUICK_XLA_FLAGS, USER_XLA_FLAGS, as_a_user_runs, with_cpu_devices

_REPORT = """
import json, os, jax
from jax._src import compiler
print(json.dumps({"quick": compiler._DISABLE_MOST_OPTIMIZATIONS.value,
                  "xla_flags": os.environ.get("XLA_FLAGS", ""), "devices": jax.local_device_count()}))
"""


def _report(env: dict[str, str]) -> dict:
    done = subprocess.run([sys.executable, "-c", _REPORT], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def test_compile_settings__tests_compile_quickly_and_a_users_process_does_not():
    assert compiler._DISABLE_MOST_OPTIMIZATIONS.value  # this test process
    assert QUICK_XLA_FLAGS in os.environ["XLA_FLAGS"]
    started = _report(dict(os.environ))  # what a test starts inherits the quick settings
    assert started["quick"] and QUICK_XLA_FLAGS in started["xla_flags"]
    user = _report(as_a_user_runs())
    assert not user["quick"] and QUICK_XLA_FLAGS not in user["xla_flags"]
    assert user["xla_flags"] == os.environ[USER_XLA_FLAGS]  # the user's own flags, kept
    two = _report(with_cpu_devices(2))
    assert two["devices"] == 2 and two["quick"] and QUICK_XLA_FLAGS in two["xla_flags"]
