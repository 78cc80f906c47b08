"""The kernels' switches (torchmm.kernels.enabled, set_enabled, switched_off; issue 44): a flag is a
bool, a kernel name one of ``kernels.names()``, and every caller in the repository passes one.

Before issue 44 ``set_enabled(name, "no")`` switched the kernel on (truthiness), ``set_enabled(name, 0)``
was accepted and ``enabled("bogus")`` said True.
"""

from __future__ import annotations

import ast
import contextlib
from pathlib import Path

import pytest

from torchmm import kernels

NAME = "particle_stages"
ROOT = Path(__file__).resolve().parents[2]


@contextlib.contextmanager
def _restored():
    before = {name: kernels.enabled(name) for name in kernels.names()}
    try:
        yield
    finally:
        for name, on in before.items():
            kernels.set_enabled(name, on)


@pytest.mark.parametrize("flag", ["no", "yes", 0, 1, None, 1.0])
def test_a_flag_is_a_bool(flag):
    with _restored():
        kernels.set_enabled(NAME, False)
        with pytest.raises(TypeError, match=r"^enabled: expected True or False"):
            kernels.set_enabled(NAME, flag)
        assert kernels.enabled(NAME) is False  # unchanged: 'no' did not switch it on
        kernels.set_enabled(NAME, True)
        assert kernels.enabled(NAME) is True


@pytest.mark.parametrize("call", [
    lambda name: kernels.enabled(name),
    lambda name: kernels.set_enabled(name, False),
    lambda name: kernels.set_enabled(name),
])
@pytest.mark.parametrize("name, error", [("bogus", ValueError), ("", ValueError), (1, TypeError),
                                         (None, TypeError), (["linear_gaussian"], TypeError)])
def test_an_unknown_kernel_name_is_refused_listing_the_kernels(call, name, error):
    with _restored(), pytest.raises(error, match=r"^name: ") as info:
        call(name)
    assert "linear_gaussian" in str(info.value) and NAME in str(info.value)  # the known kernels


@pytest.mark.parametrize("names, error, where", [
    (("bogus",), ValueError, r"names\[0\]"),
    (("linear_gaussian", "bogus"), ValueError, r"names\[1\]"),
    ((NAME, 3), TypeError, r"names\[1\]"),
])
def test_switched_off_refuses_unknown_names_and_switches_nothing(names, error, where):
    with _restored():
        before = {name: kernels.enabled(name) for name in kernels.names()}
        with pytest.raises(error, match=rf"^{where}: .*linear_gaussian"):
            with kernels.switched_off(*names):
                pass
        assert {name: kernels.enabled(name) for name in kernels.names()} == before


def test_the_switches_work():
    with _restored():
        for name in kernels.names():
            kernels.set_enabled(name, False)
            assert kernels.enabled(name) is False
            kernels.set_enabled(name)
            assert kernels.enabled(name) is True
            with kernels.switched_off(name):
                assert kernels.enabled(name) is False
            assert kernels.enabled(name) is True


def _kernel_names_passed() -> list[tuple[str, int, str]]:
    """Every string literal passed to ``set_enabled``, ``switched_off`` or ``<kernels>.enabled`` in the
    library, the study layer and the benchmarks (the tests pass invalid names on purpose)."""
    found = []
    for folder in ("torchmm", "experiments", "benchmarks", "examples"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, ast.Call):
                    continue
                func = node.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
                if name not in ("set_enabled", "switched_off", "enabled"):
                    continue
                if name == "enabled" and not (isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name)
                                              and func.value.id in ("kernels", "seam")):
                    continue
                for arg in node.args[: None if name == "switched_off" else 1]:
                    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                        found.append((str(path.relative_to(ROOT)), node.lineno, arg.value))
    return found


def test_every_caller_in_the_repository_passes_a_known_kernel_name():
    found = _kernel_names_passed()
    assert any(value == NAME for _, _, value in found)  # the scan sees the callers (experiments/run.py)
    unknown = [f"{path}:{line}: {value!r}" for path, line, value in found if value not in kernels.names()]
    assert not unknown, f"unknown kernel names (known: {kernels.names()}): {unknown}"


def test_switched_on_switches_on_inside_and_restores():
    name = kernels.by_size()[0]
    with kernels.switched_off(name):
        assert not kernels.enabled(name)
        with kernels.switched_on(name):
            assert kernels.enabled(name)
        assert not kernels.enabled(name)
    with pytest.raises(ValueError, match=r"^names\[0\]"):
        with kernels.switched_on("bogus"):
            pass
