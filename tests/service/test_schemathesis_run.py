"""schemathesis' own command against a live server, as an outsider runs it: every check in every
phase, the stateful links included, with and without a token (derandomised; docs/service.md has
the longer exploration over random seeds). Its own module so that the test run schedules it beside
the in-process contract tests (tests/service/test_openapi_contract.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

TOKEN = "contract-test-token"


SCHEMATHESIS_CONFIG = Path(__file__).with_name("schemathesis.toml")


@pytest.mark.parametrize("token", [None, TOKEN], ids=["no-token", "token"])
def test_openapi__schemathesis_every_check_every_phase_finds_nothing(tmp_path, token):
    """schemathesis' own command, as an outsider runs it against a live server: every check
    (conformance, positive and negative data, methods the path does not serve, ``Allow``,
    missing and ignored auth, the events of a stream) in every phase (examples, coverage, fuzzing
    and the stateful links), derandomised so CI cannot turn red on a lucky draw (docs/service.md:
    the longer run over random seeds). The relaxations are in ``schemathesis.toml``, with their
    reasons. The failed-authentication limit is raised: the run sends thousands of requests
    without the token, and the limiter has its own tests. The event streams are fuzzed in the
    token's run (a queued job's stream is quiet until the run's timeout for it ends it)."""
    from tests.service.conftest import LiveServer

    settings = {"api_token": token, "auth_failures_max": 100_000} if token else {}
    with LiveServer(tmp_path, **settings) as live:
        command = [str(Path(sys.executable).with_name("st")), "--no-color", "--config-file",
                   str(SCHEMATHESIS_CONFIG), "run", f"{live.url}/openapi.json", "--checks", "all",
                   "--generation-deterministic", "--max-examples", "5"]  # fmt: skip
        if token:
            command += ["--header", f"Authorization: Bearer {token}"]
        else:
            command += ["--exclude-path-regex", "/events$"]
        done = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    summary = done.stdout[done.stdout.rfind("SUMMARY"):]
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-2000:]
    assert "Stateful" in summary and " passed" in summary and "failure" not in summary, summary
    assert ("25/25" if token else "24/25") in summary, summary  # every operation was tested
