"""The layout's rules, checked on the code itself (ARCHITECTURE.md's "rules of the house"):

- the library imports no web framework, Redis or gRPC (it works with them blocked);
- nothing outside ``quicknav_core/env/`` touches a private name of the env;
- the library's modules, and its packages, import each other without cycles (lazy imports count
  too), and so do the service's modules;
- the library keeps no module-level mutable state (the Runtime holds it);
- pictures are drawn only in the render and pictures modules, never in the code that computes the
  numbers they show;
- the tests start no child process with an output pipe they never read.
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


# the modules that draw (matplotlib): the env's frames, and the pictures of evaluations, of training
# and sweeps, and of the env benchmark, and drawing (a failed picture's figures closed);
# deferred_imports only names matplotlib.pyplot to defer it
DRAWING = {"quicknav_core.env.render", "quicknav_core.eval.pictures", "quicknav_core.train.pictures",
           "quicknav_core.bench.pictures", "quicknav_core.drawing"}  # fmt: skip


def test_library__draws_only_in_its_render_and_pictures_modules():
    drawing = set()
    for name, path in {**_modules(LIBRARY), **_modules(ROOT / "quicknav_service")}.items():
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])  # fmt: skip
            if any(n == "matplotlib" or n.startswith("matplotlib.") for n in names):
                drawing.add(name)
    assert drawing == DRAWING, f"drawing outside the render/pictures modules: {sorted(drawing - DRAWING)}"


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
    assert "quicknav_core.env.constants" in graph["quicknav_core.env.numpy_env"]  # the scan works
    assert "quicknav_core.env.room_sources" in graph["quicknav_core.env.numpy_env"]  # lazy ones too
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


def _package_cycles(graph: dict[str, set[str]], depth: int) -> list[str]:
    """Cycles between packages (module names cut to ``depth`` parts)."""
    cut = lambda m: ".".join(m.split(".")[:depth])  # noqa: E731
    edges: dict[str, set[str]] = {}
    for a, targets in graph.items():
        for b in targets:
            if cut(a) != cut(b):
                edges.setdefault(cut(a), set()).add(cut(b))
    cycles = []
    for start in sorted(edges):
        stack, seen = [(start, [start])], set()
        while stack:
            node, path = stack.pop()
            for nxt in sorted(edges.get(node, ())):
                if nxt == start:
                    cycles.append(" -> ".join([*path, nxt]))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*path, nxt]))
    return sorted(set(cycles))


def test_library__its_packages_import_each_other_in_one_direction():
    """config -> env (``EnvConfig.build``), never back; eval -> train (loading runs), never back."""
    cycles = _package_cycles(_import_graph(), depth=2)
    assert not cycles, "\n".join(cycles)


def _service_graph() -> dict[str, set[str]]:
    modules = _modules(ROOT / "quicknav_service")
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in _outside_type_checking(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = name.split(".") if is_package else name.split(".")[:-1]
                    pkg = pkg[: len(pkg) - node.level + 1]
                    base = ".".join([*pkg, base] if base else pkg)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]  # fmt: skip
            graph[name] |= {t for t in targets if t in modules and t != name}
    return graph


def test_service__modules_import_each_other_without_cycles():
    """Function-level imports count: the worker imports the job kinds, never the other way (a
    runner gets a JobContext), and the Policy servicer shares helpers, not the Rollout servicer's."""
    graph = _service_graph()
    assert "quicknav_service.job_kinds" in graph["quicknav_service.worker"]  # the scan works
    cycles = _package_cycles(graph, depth=99)
    assert not cycles, "\n".join(cycles)


MUTATING = {"setdefault", "pop", "update", "append", "clear", "add", "extend", "insert", "remove",
            "popitem", "discard", "__setitem__", "appendleft"}  # fmt: skip


def module_state(path: Path) -> list[str]:
    """Module-level mutable state of one module: ``global`` statements, caches (``lru_cache``,
    ``cache``) on functions, and module-level containers that a function changes."""
    tree = ast.parse(path.read_text())
    containers = set()
    for node in tree.body:
        value = getattr(node, "value", None)
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) else [])  # fmt: skip
        made = isinstance(value, ast.Dict | ast.List | ast.Set | ast.DictComp | ast.ListComp | ast.SetComp) or (
            isinstance(value, ast.Call) and isinstance(value.func, ast.Name)
            and value.func.id in ("dict", "list", "set", "defaultdict", "OrderedDict", "deque"))  # fmt: skip
        containers |= {t.id for t in targets if isinstance(t, ast.Name) and made}
    found = []
    for node in ast.walk(tree):
        shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
        where = f"{shown}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, ast.Global):
            found.append(f"{where} global {', '.join(node.names)}")
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            caches = [ast.unparse(d) for d in node.decorator_list if "cache" in ast.unparse(d)
                      and "cached_property" not in ast.unparse(d)]  # fmt: skip
            found += [f"{where} @{c} on {node.name}" for c in caches]
            for inner in ast.walk(node):
                call = isinstance(inner, ast.Call) and isinstance(inner.func, ast.Attribute)
                if call and isinstance(inner.func.value, ast.Name) and inner.func.value.id in containers \
                        and inner.func.attr in MUTATING:  # fmt: skip
                    found.append(f"{where} {inner.func.value.id}.{inner.func.attr}()")
                targets = (inner.targets if isinstance(inner, ast.Assign | ast.Delete)
                           else [inner.target] if isinstance(inner, ast.AugAssign) else [])  # fmt: skip
                found += [f"{where} {t.value.id}[...] =" for t in targets
                          if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name)
                          and t.value.id in containers]  # fmt: skip
    return found


def test_library__keeps_no_module_level_mutable_state(tmp_path):
    """Process state lives in the Runtime passed down (``quicknav_core.runtime``), never in a module:
    no globals, no caches on functions, no module-level containers that functions change."""
    bad = tmp_path / "state_probe.py"
    bad.write_text("import functools\n_CACHE = {}\n\ndef put(k, v):\n    _CACHE[k] = v\n\n"
                   "_last = None\n\ndef remember(x):\n    global _last\n    _last = x\n\n"
                   "@functools.lru_cache\ndef memo(x):\n    return x\n")  # fmt: skip
    assert len(module_state(bad)) == 3, module_state(bad)  # the scan sees every kind
    found = [f for path in sorted(LIBRARY.rglob("*.py")) for f in module_state(path)]
    assert not found, "\n".join(found)


def test_tests__start_no_process_with_a_pipe_they_never_read():
    """A child started with ``subprocess.Popen(..., stdout=PIPE)`` and left running blocks in its
    next write once the pipe holds 64 KiB (a server then stops answering): tests start long-lived
    children with ``tests.processes.LoggedProcess`` (a log file), or send the output to a file or
    DEVNULL. ``subprocess.run`` reads its pipes and is not affected."""
    found = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "Popen"):
                continue
            for kw in node.keywords:
                if kw.arg in ("stdout", "stderr") and ast.unparse(kw.value) in ("subprocess.PIPE", "PIPE"):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found, f"Popen with an output pipe (use tests.processes.LoggedProcess): {found}"
