"""What a user installs: the wheels as built (``uv build``), their dependencies against the code's
imports, and the version, which has one source (each pyproject.toml) and is shown everywhere."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
import zipfile
from importlib.metadata import packages_distributions, version
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("quicknav_core", "quicknav_cli", "quicknav_service")


@pytest.fixture(scope="module")
def wheels(tmp_path_factory) -> dict[str, zipfile.ZipFile]:
    out = tmp_path_factory.mktemp("wheels")
    for project in (ROOT, ROOT / "clients"):
        done = subprocess.run(["uv", "build", "--wheel", "--out-dir", str(out), str(project)],
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
    return {p.name.split("-")[0]: zipfile.ZipFile(p) for p in out.glob("*.whl")}


def test_wheel__installs_only_the_projects_own_namespaced_packages_with_their_types(wheels):
    names = wheels["quicknav"].namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == set(PACKAGES), tops  # no top-level `service` to collide with anyone's
    assert "quicknav_core/py.typed" in names
    assert "quicknav_service/web/static/app.js" in names  # the browser view ships with it
    client = wheels["quicknav_client"].namelist()
    assert "quicknav_client/py.typed" in client
    assert any(n.startswith("quicknav_client/") and n.endswith("_pb2.py") for n in client)


def _third_party_imports(package: Path, skip: tuple[str, ...] = ()) -> set[str]:
    found = set()
    for path in package.rglob("*.py") if package.is_dir() else [package]:
        if path.name in skip:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                found.add(node.module.split(".")[0])
    own = {*PACKAGES, "quicknav_client", "tests", "__future__"}
    return {m for m in found - own if m not in sys.stdlib_module_names}


def _requirement_names(requirements: list[str]) -> set[str]:
    return {re.split(r"[\s<>=!~\[;]", r, maxsplit=1)[0].lower().replace("_", "-") for r in requirements}


def test_dependencies__what_is_imported_is_declared_and_what_is_declared_is_used():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = _requirement_names(project["dependencies"])
    extras = project["optional-dependencies"]
    service = core | _requirement_names(extras["service"])
    if "quicknav[export]" in extras["service"]:  # the service extra includes the export one
        service |= _requirement_names(extras["export"])
    dist_of = packages_distributions()
    # an optional import guarded where it is used (a faster path when present); jaxlib is jax's
    # own requirement (read only for its version string)
    optional = {"numba", "torch", "jaxlib"}

    def undeclared(imported: set[str], declared: set[str]) -> dict[str, list[str]]:
        out = {}
        for module in sorted(imported - optional):
            dists = {d.lower().replace("_", "-") for d in dist_of.get(module, [module])}
            if not dists & declared:
                out[module] = sorted(dists)
        return out

    # the export module alone may import the `export` extra (the CLI says to install it)
    library = _third_party_imports(ROOT / "quicknav_core", skip=("export.py",))
    assert not undeclared(library, core), (
        f"imported by quicknav_core but not in [project.dependencies]: {undeclared(library, core)}")  # fmt: skip
    export = core | _requirement_names(project["optional-dependencies"]["export"])
    exporting = _third_party_imports(ROOT / "quicknav_core" / "export.py")
    assert not undeclared(exporting, export), undeclared(exporting, export)
    assert "quicknav[export]" in project["optional-dependencies"]["service"]  # workers export
    library |= exporting
    rest = _third_party_imports(ROOT / "quicknav_cli") | _third_party_imports(ROOT / "quicknav_service")
    assert not undeclared(rest, service), (
        f"imported by the CLI or the service but not declared: {undeclared(rest, service)}")  # fmt: skip
    used = {d.lower().replace("_", "-") for m in library | rest for d in dist_of.get(m, [])}
    unused = core - used
    assert not unused, f"in [project.dependencies] but never imported: {unused}"


def test_version__one_source_shown_by_the_cli_the_api_and_the_sdk():
    import quicknav_client

    import quicknav_core
    from quicknav_service.api.main import api_version

    root = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    client = tomllib.loads((ROOT / "clients" / "pyproject.toml").read_text())["project"]["version"]
    assert quicknav_core.__version__ == version("quicknav") == root
    assert quicknav_client.__version__ == version("quicknav-client") == client
    assert api_version() == root  # the OpenAPI document's info.version
    for path in [*ROOT.glob("quicknav_*/**/*.py"), *(ROOT / "clients").glob("quicknav_client/**/*.py")]:
        text = path.read_text()
        assert f'"{root}"' not in text and f'"{client}"' not in text, f"{path} writes the version out"
