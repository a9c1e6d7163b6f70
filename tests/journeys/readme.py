"""README's journeys, read out of the Markdown and run as a user runs them.

A journey is the fenced ``bash`` blocks that follow an HTML comment ``<!-- journey: NAME -->``
(invisible on GitHub and in the docs site), in the order they appear in README.md and then in
docs/*.md. Sybil's Markdown lexer finds the fenced blocks; this module only decides which of them
belong to a journey and runs their lines one by one, as they are written, with these stand-ins:

- ``uv sync`` is not run again: the tests already run inside the synced environment (and syncing
  it under a test session that uses it would be a race). Every ``uv run`` gets ``UV_NO_SYNC=1`` for
  the same reason, and ``UV_PROJECT`` so that it finds this checkout from a scratch folder.
- ``uv run quicknav serve`` starts in the background on free ports, told them the way a user tells
  it (``QUICKNAV_PORT``, ``QUICKNAV_GRPC_PORT``, ``QUICKNAV_DATA_DIR``); ``localhost:8000`` in a
  command becomes that address, and the ``quicknav jobs`` commands find it through ``QUICKNAV_URL``.
  The journeys of one test module share one such service (``Runner.attach``): a journey's own
  ``serve`` line then finds it running.
- ``uv run quicknav train --preset demo``, where a test hands the runner the test run's trained
  demo (``trained``): ``tests/trained.py`` ran this very command once for the whole test run, and
  its run folder is copied where the command writes it (one training to target per test run).
- ``<id>`` is the job id the command before printed, cut to its first 8 characters (the short id
  a user copies); ``<eval-id>`` the id ``quicknav jobs submit eval`` printed, cut the same way; ``<run-dir>`` is the run folder ``quicknav train`` printed; ``<map-id>`` the map
  id ``quicknav maps upload`` printed.
- a ``curl`` line gets ``-w`` with the HTTP status appended, so that each one is checked for it.
- a ``python`` block runs as a script (``uv run python -``), with ``127.0.0.1:8000`` and
  ``127.0.0.1:50051`` turned into the service's HTTP and gRPC addresses.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from sybil import Document
from sybil.parsers.markdown.lexers import FencedCodeBlockLexer

from tests.compile_settings import as_a_user_runs
from tests.processes import LoggedProcess

ROOT = Path(__file__).resolve().parents[2]
MARKER = re.compile(r"<!--\s*journey:\s*(?P<name>[\w-]+)\s*-->\s*\Z")
JOB_ID = re.compile(r"\b[0-9a-f]{32}\b")
RUN_DIR = re.compile(r"run folder: (?P<dir>\S+)")
MAP_ID = re.compile(r"^map (?P<id>[0-9a-f]{16}) ", re.M)
STATUS = re.compile(r"\[http (?P<code>\d{3})\]\s*\Z")


@dataclass
class Block:
    """A fenced code block of README.md or a docs page; ``journey`` is its marker's name, if any."""

    journey: str | None
    path: Path
    line: int
    language: str
    source: str

    @property
    def commands(self) -> list[str]:
        return _commands(self.source)

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT) if self.path.is_relative_to(ROOT) else self.path}:{self.line}"


def doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("**/*.md"))]


def _commands(source: str) -> list[str]:
    """A block's command lines: continuation lines joined, blank and comment-only lines left out."""
    lines, pending = [], ""
    for raw in source.splitlines():
        line = pending + raw
        if line.rstrip().endswith("\\"):
            pending = line.rstrip()[:-1] + " "
            continue
        pending = ""
        if line.strip() and not line.lstrip().startswith("#"):
            lines.append(line.strip())
    return lines


def code_blocks(files: list[Path] | None = None) -> list[Block]:
    """Every fenced code block of the pages, in reading order, with its journey marker if it has one."""
    blocks = []
    for path in files or doc_files():
        text = path.read_text()
        document = Document(text, str(path))
        for region in FencedCodeBlockLexer(r"[\w-]*")(document):
            before = text[: region.start].rstrip(" ")
            marker = MARKER.search(before.removesuffix("\n"))
            blocks.append(Block(marker["name"] if marker else None, path,
                                text.count("\n", 0, region.start) + 1,
                                region.lexemes["language"] or "", str(region.lexemes["source"])))  # fmt: skip
    return blocks


def journey_blocks(files: list[Path] | None = None) -> list[Block]:
    """Every block marked as part of a journey, in reading order."""
    blocks = [b for b in code_blocks(files) if b.journey is not None]
    for b in blocks:
        assert b.language in ("bash", "python"), (
            f"{b.where}: a journey block must be bash or python, not {b.language!r}")  # fmt: skip
    return blocks


def journey(name: str) -> list[Block]:
    return [b for b in journey_blocks() if b.journey == name]


@dataclass
class Ran:
    command: str
    ran: str
    code: int
    stdout: str
    stderr: str
    seconds: float

    def __str__(self) -> str:
        return (f"$ {self.command}\n(ran: {self.ran})\nexit {self.code} after {self.seconds:.1f} s\n"
                f"--- stdout\n{self.stdout[-4000:]}\n--- stderr\n{self.stderr[-4000:]}")  # fmt: skip


@dataclass
class Runner:
    """Runs journey commands in ``workdir`` against a service it starts on free ports."""

    workdir: Path
    port: int
    grpc_port: int
    timeout_s: float = 600.0
    last_id: str | None = None
    run_dir: str | None = None
    map_id: str | None = None
    eval_id: str | None = None
    history: list[Ran] = field(default_factory=list)
    server: LoggedProcess | None = None
    shared: Runner | None = None  # the module's service this runner's commands talk to
    trained: dict[str, Path] = field(default_factory=dict)  # command -> the run folder it made

    def attach(self, service: Runner) -> Runner:
        """Talk to ``service`` (a running ``quicknav serve`` of another runner) instead of
        starting one."""
        self.port, self.grpc_port, self.shared = service.port, service.grpc_port, service
        return self

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def env(self) -> dict[str, str]:
        # a user's shell: none of the test run's settings, its compile settings included
        env = {k: v for k, v in as_a_user_runs().items() if not k.startswith("QUICKNAV_")}
        env.update(UV_NO_SYNC="1", UV_PROJECT=str(ROOT), COLUMNS="80", NO_COLOR="1",
                   QUICKNAV_URL=self.url, QUICKNAV_PORT=str(self.port),
                   QUICKNAV_GRPC_PORT=str(self.grpc_port),
                   QUICKNAV_DATA_DIR=str(self.workdir / "data"))  # fmt: skip
        return env

    def substitute(self, command: str) -> str:
        if "<id>" in command:
            assert self.last_id, f"{command!r} needs a job id, and no command before printed one"
            command = command.replace("<id>", self.last_id[:8])
        if "<eval-id>" in command:
            assert self.eval_id, f"{command!r} needs an eval job's id, and no `jobs submit eval` ran"
            command = command.replace("<eval-id>", self.eval_id[:8])
        if "<map-id>" in command:
            assert self.map_id, f"{command!r} needs a map id, and no upload printed one"
            command = command.replace("<map-id>", self.map_id)
        if "<run-dir>" in command:
            assert self.run_dir, f"{command!r} needs a run folder, and no train printed one"
            command = command.replace("<run-dir>", shlex.quote(self.run_dir))
        for host in ("localhost:8000", "127.0.0.1:8000"):
            command = command.replace(host, f"127.0.0.1:{self.port}")
        return command

    def run(self, command: str) -> Ran | None:
        words = shlex.split(command, comments=True)
        if words[:2] == ["uv", "sync"]:
            return None  # see the module's docstring
        if words[:4] == ["uv", "run", "quicknav", "serve"]:
            self.start_server(command)
            return None
        if " ".join(words) in self.trained:
            return self.trained_stand_in(command, self.trained[" ".join(words)])
        assert words[:3] == ["uv", "run", "quicknav"] or words[0] == "curl", (
            f"the journey runner does not know how to run {command!r}"
        )
        ran = self.substitute(command)
        if words[0] == "curl":
            code_part, _, comment = ran.partition(" #")
            ran = f"{code_part} -w '\\n[http %{{http_code}}]'" + (f" #{comment}" if comment else "")
        t0 = time.time()
        done = subprocess.run(["bash", "-c", ran], cwd=self.workdir, env=self.env(),
                              capture_output=True, text=True, timeout=self.timeout_s)  # fmt: skip
        result = Ran(command, ran, done.returncode, done.stdout, done.stderr, time.time() - t0)
        self.history.append(result)
        ids = JOB_ID.findall(done.stdout)
        if ids:
            self.last_id = ids[-1]
            if "jobs submit eval" in command:
                self.eval_id = ids[-1]
        found = RUN_DIR.search(done.stdout)
        if found:
            self.run_dir = found["dir"]
        if uploaded := MAP_ID.search(done.stdout):
            self.map_id = uploaded["id"]
        return result

    def run_python(self, source: str) -> Ran:
        """A python block of a page, run as a script in the scratch folder."""
        script = source.replace("127.0.0.1:8000", f"127.0.0.1:{self.port}")
        script = script.replace("127.0.0.1:50051", f"127.0.0.1:{self.grpc_port}")
        t0 = time.time()
        done = subprocess.run(["uv", "run", "python", "-"], input=script, cwd=self.workdir,
                              env=self.env(), capture_output=True, text=True, timeout=self.timeout_s)  # fmt: skip
        result = Ran(source.strip().splitlines()[0], script, done.returncode, done.stdout,
                     done.stderr, time.time() - t0)  # fmt: skip
        self.history.append(result)
        return result

    def trained_stand_in(self, command: str, run: Path) -> Ran:
        """The run folder ``command`` makes, copied from where the test run's one training of it
        left it (see the module's docstring)."""
        import shutil

        target = self.workdir / "runs" / run.name
        shutil.copytree(run, target)
        self.run_dir = str(target.relative_to(self.workdir))
        result = Ran(command, f"(the test run's trained demo: {run})", 0,
                     f"run folder: {self.run_dir}\n", "", 0.0)  # fmt: skip
        self.history.append(result)
        return result

    def start_server(self, command: str) -> None:
        if self.shared is not None:  # the module's service already runs this command
            assert httpx.get(f"{self.url}/healthz", timeout=5).status_code == 200
            return
        assert self.server is None, "the journey starts the service twice"
        self.server = LoggedProcess(["bash", "-c", f"exec {command.partition(' #')[0]}"],
                                    cwd=self.workdir, env=self.env(), start_new_session=True)
        deadline = time.time() + 120
        while True:
            try:
                if httpx.get(f"{self.url}/healthz", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if self.server.poll() is not None or time.time() > deadline:
                out = self.server.output()
                raise AssertionError(f"`{command}` did not come up on {self.url}:\n{out}")
            time.sleep(0.3)

    def stop(self) -> str:
        """Stop the service (SIGTERM, as Ctrl-C would); its output."""
        if self.server is None:
            return ""
        server, self.server = self.server, None
        os.killpg(server.pid, signal.SIGTERM)
        try:
            return server.finish(60)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            return server.finish(60)


def http_status(ran: Ran) -> int:
    found = STATUS.search(ran.stdout)
    assert found, f"no status written by curl:\n{ran}"
    return int(found["code"])
