"""Every code block of README.md and the docs site is checked against what it describes, so that a
page cannot drift from the code:

- every ``uv run quicknav ...`` line is parsed by the real command line (its options, choices and
  arguments; the commands' bodies are replaced by a recorder, so nothing trains);
- every other command names something that exists (an executable of the environment, a script of
  the repository), and every ``curl`` line names a route the API has, with a method it answers
  and a body its request model accepts;
- every ``python`` block compiles and what it imports exists; the blocks of the ``library``
  journey run here, in-process, and the service pages' journeys run against a live server in
  ``test_readme_journeys.py``;
- a ``console`` block's commands are run and print what the page shows.
"""

from __future__ import annotations

import ast
import importlib
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from quicknav_cli.main import app as cli_app
from tests.journeys.readme import ROOT, Block, code_blocks, journey

SHELL = ("bash", "sh")
# languages of blocks that are not code to check: directory trees, plain text
TEXT = ("text", "")


def blocks(*languages: str) -> list[Block]:
    return [b for b in code_blocks() if b.language in languages]


def cli_calls(args: list[str]) -> list[tuple[str, dict]]:
    """The commands ``quicknav ARGS`` would call, with their parsed parameters, calling none."""
    root = typer.main.get_command(cli_app)
    called: list[tuple[str, dict]] = []

    def recorder(name: str):
        return lambda *a, **params: called.append((name, params))

    def stub(command) -> None:
        if command.callback is not None:
            command.callback = recorder(command.name)
        for sub in getattr(command, "commands", {}).values():
            stub(sub)

    stub(root)
    root.main(list(args), prog_name="quicknav", standalone_mode=False)
    return called


def shell_lines() -> list[tuple[Block, str]]:
    out = [(b, c) for b in blocks(*SHELL) for c in b.commands]
    out += [(b, line[2:]) for b in blocks("console") for line in b.source.splitlines()
            if line.startswith("$ ")]  # fmt: skip
    return out


def test_docs__every_block_has_a_language_the_checks_know():
    for b in code_blocks():
        assert b.language in (*SHELL, "console", "python", *TEXT), (
            f"{b.where}: a ```{b.language} block: no check here knows what to do with it")  # fmt: skip
    assert blocks(*TEXT) == [b for b in code_blocks() if b.language == "text"], (
        [b.where for b in blocks("")], "give every block a language (text for a directory tree)")


def test_docs__every_quicknav_command_on_a_page_is_one_the_cli_accepts(capsys):
    checked = 0
    for block, line in shell_lines():
        words = shlex.split(line, comments=True)
        if words[:3] != ["uv", "run", "quicknav"]:
            continue
        try:
            called = cli_calls(words[3:])
        except Exception as e:  # click's UsageError and its kin, under typer's vendored click
            message = e.format_message() if hasattr(e, "format_message") else repr(e)
            raise AssertionError(f"{block.where}: `{line}` is refused by the CLI: {message}") from e
        assert len(called) >= 2, (  # the root callback, then the command itself
            f"{block.where}: `{line}` did not reach a command: {capsys.readouterr().err}")
        checked += 1
    assert checked >= 20, checked


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    """The API in-process with no workers, and the id of a cancelled job for ``<id>`` (its event
    stream ends at once; an eval of it is refused for its state, after its body was accepted)."""
    from fastapi.testclient import TestClient

    from quicknav_service.api.main import create_app
    from quicknav_service.settings import Settings

    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("docs-api")), start_workers=False)
    with TestClient(app) as client:
        job = client.post("/jobs/train", json={"preset": "demo"}).json()["id"]
        client.post(f"/jobs/{job}/cancel", json={})
        yield client, job


def _curl(api, block: Block, line: str) -> None:
    """Send what a curl line sends to the API: the route must exist, answer the method and accept
    the body's fields (a refusal for the job's state is fine: the cancelled job stands in)."""
    client, job = api
    if "<map-id>" in line:  # a map the page uploaded before: the shipped office map stands in
        files = [("files", (p.name, p.read_bytes())) for p in
                 (ROOT / "examples/maps/office.yaml", ROOT / "examples/maps/office.pgm")]  # fmt: skip
        line = line.replace("<map-id>", client.post("/maps", files=files).json()["id"])
    words = shlex.split(line.replace("<id>", job), comments=True)
    method, url, body, form = "GET", None, None, []
    for i, w in enumerate(words):
        if w == "-X":
            method = words[i + 1]
        elif w in ("-d", "--data", "--data-raw"):
            body = words[i + 1]
            method = "POST" if method == "GET" else method
        elif w in ("-F", "--form"):  # name=@file (read from the repository) or name=value
            form.append(words[i + 1].split("=", 1))
            method = "POST" if method == "GET" else method
        elif "localhost:" in w or w.startswith("http"):
            url = w
    assert url, f"{block.where}: `{line}` has no address"
    path = re.sub(r"^(https?://)?[^/]+", "", url)
    if form:
        files = [(k, (Path(v[1:]).name, (ROOT / v[1:]).read_bytes())) for k, v in form if v.startswith("@")]
        data = {k: v for k, v in form if not v.startswith("@")}
        answer = client.request(method, path, files=files, data=data)
    else:
        answer = client.request(method, path, content=body,
                                headers={"content-type": "application/json"} if body else {})  # fmt: skip
    refused = answer.status_code in (400, 405, 422) or (
        answer.status_code == 404 and answer.json().get("detail") == "Not Found")  # fmt: skip
    assert not refused, f"{block.where}: `{line}`: {answer.status_code} {answer.text}"


def test_docs__every_other_command_names_something_that_exists(api):
    scripts, curls = set(), 0
    for block, line in shell_lines():
        words = shlex.split(line, comments=True)
        while words and re.fullmatch(r"[A-Z_]+=\S*", words[0]):  # VAR=value before the command
            words = words[1:]
        if words[:3] == ["uv", "run", "quicknav"] or words[:2] == ["uv", "sync"]:
            continue
        if words[0] == "curl":
            _curl(api, block, line)
            curls += 1
        elif words[:3] == ["uv", "run", "python"] or words[0] in ("python3", "bash"):
            rest = words[3:] if words[0] == "uv" else words[1:]
            if rest[:2] == ["-m", "pip"]:
                continue
            assert (ROOT / rest[0]).is_file(), f"{block.where}: `{line}`: no {rest[0]} in the repository"
            scripts.add(rest[0])
        elif words[:2] == ["uv", "run"]:
            exe = Path(sys.executable).parent / words[2]
            assert exe.exists(), f"{block.where}: `{line}`: {words[2]} is not installed by `uv sync`"
        else:
            raise AssertionError(f"{block.where}: `{line}`: nothing here checks this command")
    assert scripts and curls >= 4, "no script or curl lines found: the check lost its input"


def _imports(tree: ast.AST) -> list[tuple[str, str | None]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out += [(node.module, a.name) for a in node.names]
    return out


def test_docs__python_blocks_compile_and_what_they_import_exists():
    found = blocks("python")
    assert len(found) >= 4
    for b in found:
        try:
            tree = ast.parse(b.source)
        except SyntaxError as e:
            raise AssertionError(f"{b.where}: the block does not compile: {e}") from e
        for module, name in _imports(tree):
            imported = importlib.import_module(module)
            assert name is None or hasattr(imported, name) or importlib.util.find_spec(
                f"{module}.{name}") is not None, f"{b.where}: {module} has no {name}"  # fmt: skip


def test_docs__library_blocks_run_as_written():
    ran = journey("library")
    assert ran, "docs/environment.md lost its `library` journey marker"
    for b in ran:
        assert b.language == "python"
        namespace: dict = {}
        exec(compile(b.source, b.where, "exec"), namespace)
        assert namespace, b.where


def test_docs__console_examples_print_what_the_page_shows(tmp_path):
    examples = blocks("console")
    assert examples
    for b in examples:
        lines = b.source.splitlines()
        starts = [i for i, line in enumerate(lines) if line.startswith("$ ")]
        for k, i in enumerate(starts):
            command = lines[i][2:]
            expected = lines[i + 1: starts[k + 1] if k + 1 < len(starts) else len(lines)]
            words = shlex.split(command)
            assert words[:3] == ["uv", "run", "quicknav"], f"{b.where}: `{command}`"
            done = subprocess.run([sys.executable, "-m", "quicknav_cli", *words[3:]], cwd=tmp_path,
                                  capture_output=True, text=True, timeout=300)  # fmt: skip
            printed = [" ".join(x.split()) for x in (done.stdout + done.stderr).splitlines()]
            for want in expected:
                assert " ".join(want.split()) in printed, (
                    f"{b.where}: `{command}` no longer prints\n  {want.strip()}\nit printed:\n"
                    + "\n".join(printed))  # fmt: skip


@pytest.mark.parametrize("name", ["library", "service-http", "sdk", "grpc", "building"])
def test_docs__each_docs_journey_is_marked(name):
    assert journey(name), f"no block of the docs is marked `<!-- journey: {name} -->`"
