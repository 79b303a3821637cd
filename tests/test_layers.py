"""The layers point one way (docs/explanation/architecture.md): ``riskflow_env`` imports
nothing from ``policies``, and no module imports another that imports it back."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("riskflow_env", "policies")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports() -> dict[str, set[str]]:
    """Every module of PACKAGES -> the modules of PACKAGES it imports anywhere (function
    bodies included): ``from a.b import c`` names ``a.b.c`` when that is a module."""
    files = {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                for alias in node.names:
                    full = f"{base}.{alias.name}"
                    targets.add(full if full in files else base)
        graph[name] = {t for t in targets if t in files and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in sorted(graph[node]):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_env_imports_nothing_from_policies():
    upward = {
        module: sorted(t for t in targets if t.split(".")[0] == "policies")
        for module, targets in module_imports().items()
        if module.split(".")[0] == "riskflow_env"
    }
    assert not {m: t for m, t in upward.items() if t}


def test_every_env_module_imports_with_policies_unavailable():
    """Imports every module of ``riskflow_env`` in a fresh interpreter where importing
    ``policies`` raises."""
    script = """
import importlib, pkgutil, sys

class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name == "policies" or name.startswith("policies."):
            raise ImportError(f"riskflow_env imported {name}")

sys.meta_path.insert(0, Refuse())
import riskflow_env
for info in pkgutil.walk_packages(riskflow_env.__path__, "riskflow_env."):
    importlib.import_module(info.name)
env = riskflow_env.parallel_env()
from riskflow_env.wrappers import EgoEnv
ego = EgoEnv()
ego.reset(seed=0)
ego.step(ego.action_space.sample())
print("ok", len(sys.modules))
"""
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.startswith("ok")


def _layer(module: str) -> str:
    """A module's layer: its sub-package (``policies.learned``), or the module itself when
    it sits directly in a top-level package (``policies.harness``, ``riskflow_env.env``)."""
    path = ROOT.joinpath(*module.split("."))
    if (path / "__init__.py").is_file():
        return module
    parent = module.rpartition(".")[0]
    return module if "." not in parent else parent


def test_no_module_imports_another_that_imports_it_back():
    assert cycles(module_imports()) == []


def test_no_layer_imports_another_that_imports_it_back():
    """Cycles between sub-packages hide behind lazy imports (e.g. the shared layer loading
    a baseline's model inside a function): none may exist."""
    graph: dict[str, set[str]] = {}
    for module, targets in module_imports().items():
        layer = _layer(module)
        graph.setdefault(layer, set()).update(_layer(t) for t in targets)
    graph = {
        layer: {t for t in targets if t in graph and t != layer} for layer, targets in graph.items()
    }
    assert cycles(graph) == []


def test_the_shared_layer_imports_no_adversary():
    """``policies.learned`` is what RiskFlow, STRIVE-style and the diffusion baselines
    share: it imports none of them."""
    above = ("policies.riskflow", "policies.baselines", "policies.evaluation", "policies.rl")
    upward = {
        module: sorted(t for t in targets if t.startswith(above) or t == "policies.train")
        for module, targets in module_imports().items()
        if module.startswith("policies.learned")
    }
    assert not {m: t for m, t in upward.items() if t}
