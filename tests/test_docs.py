"""Documentation stays executable: the README's Python block and every docstring example."""

from __future__ import annotations

import doctest
import importlib
import pkgutil
import re
from pathlib import Path

import pytest
import torch

import torchmm

ROOT = Path(__file__).resolve().parents[1]
MODULES = sorted(m.name for m in pkgutil.walk_packages(torchmm.__path__, "torchmm."))


def test_readme_python_block_runs():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    assert namespace["traj"].estimate().mean.shape == (100, 400, 2)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    torch.set_default_dtype(torch.float32)  # examples are written for the torch default
    module = importlib.import_module(name)
    result = doctest.testmod(module, extraglobs={"torch": torch, "GaussianBelief": torchmm.GaussianBelief},
                             optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0


def test_public_classes_carry_examples():
    finder = doctest.DocTestFinder()
    with_examples = set()
    for name in MODULES:
        for test in finder.find(importlib.import_module(name)):
            if test.examples:
                with_examples.add(test.name.rsplit(".", 1)[-1])
    assert {"KalmanFilter", "ExtendedKalmanFilter", "IMM", "GaussianBelief", "ModeTransition",
            "run_filter"} & with_examples >= {"IMM", "GaussianBelief", "ModeTransition", "run_filter"}


def _resolves(reference: str) -> bool:
    """Whether a dotted ``torchmm.x.y`` reference names an object: the longest importable module, then
    attributes."""
    parts = reference.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for name in parts[i:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


def test_docstring_cross_references_name_real_objects():
    """Every Sphinx-style reference to torchmm in the library's and the harness's sources
    (``:func:`~torchmm.smooth```, ``:class:`torchmm.filters.particle.ParticleFilter```, ...) names an object
    that exists: a module split (issue 47) or a rename leaves none pointing at a name that moved."""
    pattern = re.compile(r":(?:func|class|mod|meth|attr|data):`~?(torchmm(?:\.\w+)+)`")
    broken = []
    for folder in ("torchmm", "experiments"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for reference in set(pattern.findall(path.read_text())):
                if not _resolves(reference):
                    broken.append(f"{path.relative_to(ROOT)}: {reference}")
    assert not broken, broken
