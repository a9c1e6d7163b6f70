"""The layout's rules, checked on the code itself (ARCHITECTURE.md's "rules of the house"):

- the library imports no web framework, Redis or gRPC (it works with them blocked);
- nothing outside ``quicknav_core/env/`` touches a private name of the env;
- the library's modules import each other without cycles (lazy imports count too).
"""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "quicknav_core"
SERVICE_ONLY = ("fastapi", "starlette", "uvicorn", "redis", "grpc", "httpx", "quicknav_client",
                "quicknav_service", "quicknav_cli", "pydantic_settings")  # fmt: skip


def _modules(package: Path, root: Path = ROOT) -> dict[str, Path]:
    out = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _outside_type_checking(tree: ast.AST) -> list[ast.stmt | ast.expr]:
    """Every node of the tree except those under ``if TYPE_CHECKING:`` blocks."""
    nodes = []
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            stack.extend(node.orelse)
            continue
        nodes.append(node)
        stack.extend(ast.iter_child_nodes(node))
    return nodes


def test_library__imports_and_steps_with_the_service_stack_blocked():
    script = textwrap.dedent(f"""
        import importlib, importlib.abc, pkgutil, sys
        BLOCKED = {SERVICE_ONLY!r}

        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ImportError(f"{{name}} is blocked: the library must not import it")
                return None

        sys.meta_path.insert(0, Block())
        import quicknav_core
        names = [m.name for m in pkgutil.walk_packages(quicknav_core.__path__, "quicknav_core.")]
        for name in names:
            importlib.import_module(name)
        import jax, jax.numpy as jnp
        from quicknav_core.config import EnvConfig
        env, params = EnvConfig(grid_size=8, lidar_beams=8, train_rooms=8, test_rooms=4).build()
        obs, state = env.reset(jax.random.PRNGKey(0), params)
        obs, state, reward, done, info = env.step(jax.random.PRNGKey(1), state, jnp.ones(2), params)
        assert obs.shape == (env.obs_dim,) and bool(jnp.isfinite(reward))
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        assert not loaded, loaded
        print(len(names), "modules")
    """)
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                            text=True, timeout=300)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert int(result.stdout.split()[0]) > 30, result.stdout


def test_env__private_names_stay_inside_env():
    env_modules = _modules(LIBRARY / "env")
    private: set[str] = set()
    for path in env_modules.values():
        for node in ast.walk(ast.parse(path.read_text())):
            named = isinstance(node, ast.FunctionDef | ast.ClassDef | ast.AsyncFunctionDef)
            if named and node.name.startswith("_") and not node.name.startswith("__"):
                private.add(node.name)
    assert {"_episode_start", "_entered_bits"} <= private  # the scan sees them
    offenders = []
    outside = {**_modules(LIBRARY), **_modules(ROOT / "quicknav_cli"), **_modules(ROOT / "quicknav_service")}
    for name, path in outside.items():
        if name.startswith("quicknav_core.env"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in private:
                offenders.append(f"{name}: .{node.attr}")
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
                "quicknav_core.env"
            ):
                offenders += [f"{name}: import {a.name}" for a in node.names if a.name.startswith("_")]
    assert not offenders, offenders


def _import_graph() -> dict[str, set[str]]:
    modules = _modules(LIBRARY)
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in _outside_type_checking(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: from the package of this module
                    pkg = name.split(".") if is_package else name.split(".")[:-1]
                    pkg = pkg[: len(pkg) - node.level + 1]
                    base = ".".join([*pkg, base] if base else pkg)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]  # fmt: skip
            for target in targets:
                if target in modules and target != name:
                    graph[name].add(target)
    return graph


def test_library__imports_have_no_cycles():
    graph = _import_graph()
    assert "quicknav_core.config.env" in graph["quicknav_core.env.numpy_env"]  # the scan works
    cycles = []
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                loop = [*path[path.index(nxt) :], node, nxt] if nxt in path else [node, nxt]
                cycles.append(" -> ".join(loop))
            elif nxt not in state:
                visit(nxt, [*path, node])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [])
    assert not cycles, "\n".join(cycles)
