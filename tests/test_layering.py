"""The package layers: a lower layer never imports a higher one; no private names cross modules."""

from __future__ import annotations

import ast
from pathlib import Path

import torchmm

ROOT = Path(torchmm.__file__).parent

#: bottom to top; a package may import packages of lower layers only (docs/architecture.md)
LAYERS = [
    {"validation", "typing", "runtime", "provenance"},
    {"contract"},  # the entry-point contract (torchmm/contract.py): every layer above declares through it
    {"distributions", "linalg", "cpu_kernels"},
    {"beliefs"},
    {"models"},
    {"filters", "simulate"},
    {"run", "multimodel"},
    {"smooth", "parallel"},  # the backward passes, the time-parallel scans
    {"fusion", "learn", "metrics", "analysis"},
    {"torchmm"},  # the top-level namespace
]
LEVEL = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "torchmm"


def _imports():
    for path in ROOT.rglob("*.py"):
        module = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("torchmm"):
                yield module, node.module, [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("torchmm"):
                        yield module, alias.name, []


def test_every_package_has_a_layer():
    packages = {_package(m) for m, _, _ in _imports()} | {_package(t) for _, t, _ in _imports()}
    assert packages <= set(LEVEL), sorted(packages - set(LEVEL))


def test_lower_layers_never_import_higher_ones():
    bad = [(m, t) for m, t, _ in _imports()
           if _package(m) != _package(t) and LEVEL[_package(t)] >= LEVEL[_package(m)]]
    assert not bad, bad


def test_no_private_names_cross_modules():
    bad = [(m, t, n) for m, t, names in _imports() for n in names
           if n.startswith("_") and not n.startswith("__") and t != m]
    assert not bad, bad
