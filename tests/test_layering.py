"""The package layers: a lower layer never imports a higher one; no private names cross modules."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import torchmm

ROOT = Path(torchmm.__file__).parent

#: bottom to top; a package may import packages of lower layers only (docs/architecture.md)
LAYERS = [
    {"validation", "typing", "runtime", "unchanged"},
    {"provenance"},  # (its small tensors' checksums in NumPy: validation.host_array)
    {"contract"},  # the entry-point contract (torchmm/contract/): every layer above declares through it
    {"distributions", "linalg"},
    {"beliefs"},
    {"models"},
    {"kernels"},  # the seam (torchmm/kernels/__init__.py) and every whole-run kernel behind it (issue 47)
    {"filters", "simulate", "assignment"},  # (assignment: its compiled loop is a stage kernel)
    {"run", "multimodel", "association"},
    {"two_filter", "smooth_checks"},  # the two-filter IMM smoother; smooth's arguments checked against the
    # run that made the trajectory (both split from smooth.py, issue 47)
    {"two_filter_info"},  # the information-form two-filter smoother (method="two_filter_info")
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


# -- the study harness (experiments/) -----------------------------------------------------------------
EXPERIMENTS = ROOT.parent / "experiments"

#: import edges allowed to close a cycle in experiments/, as (importer, imported)
ALLOWED_CYCLE_EDGES: set[tuple[str, str]] = set()  # none: config -> schemas -> checks
#: private names allowed to cross modules of experiments/, as (importer, imported module, name)
ALLOWED_PRIVATE: set[tuple[str, str, str]] = set()


def _module_name(path: Path, root: Path) -> str:
    return ".".join(path.relative_to(root.parent).with_suffix("").parts).removesuffix(".__init__")


def _experiments_imports():
    """``(module, imported module, names)`` of every import in experiments/ - at the top of a module and
    inside functions alike (AST walk) - of experiments modules; ``from experiments.x import y`` where
    ``y`` is a submodule counts as an import of ``experiments.x.y``."""
    modules = {_module_name(p, EXPERIMENTS): p for p in EXPERIMENTS.rglob("*.py")}
    for module, path in sorted(modules.items()):
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: from the module's package upwards
                    parts = package.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
                if base.split(".")[0] != "experiments":
                    continue
                plain = []
                for alias in node.names:
                    if f"{base}.{alias.name}" in modules:
                        yield module, f"{base}.{alias.name}", []
                    else:
                        plain.append(alias.name)
                if plain:
                    yield module, base, plain
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] == "experiments":
                        yield module, alias.name, []


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` (its modules in order, the first repeated at the end), or None."""
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_experiments_imports_are_found():
    edges = {(m, t) for m, t, _ in _experiments_imports()}
    # a top-level import, one inside a function, and a submodule named in ``from package import module``
    assert ("experiments.context", "experiments.files") in edges
    assert ("experiments.context", "experiments.executors") in edges
    assert ("experiments.studies.imm_baseline", "experiments.studies.plots") in edges


def test_experiments_has_no_import_cycles():
    """experiments/ is a DAG of modules, counting imports inside functions (a lazy import is still a
    dependency): a module never imports, however indirectly, a module that imports it."""
    graph: dict[str, set[str]] = {}
    for module, target, _ in _experiments_imports():
        if module != target and (module, target) not in ALLOWED_CYCLE_EDGES:
            graph.setdefault(module, set()).add(target)
    cycle = _cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_allowed_exceptions_still_exist():
    """The whitelist holds only live edges (delete an entry once its cycle is gone)."""
    imports = list(_experiments_imports())
    edges = {(m, t) for m, t, _ in imports}
    assert ALLOWED_CYCLE_EDGES <= edges, ALLOWED_CYCLE_EDGES - edges
    names = {(m, t, n) for m, t, ns in imports for n in ns}
    assert ALLOWED_PRIVATE <= names, ALLOWED_PRIVATE - names


def test_experiments_import_no_private_names_of_other_modules():
    bad = [(m, t, n) for m, t, names in _experiments_imports() for n in names
           if n.startswith("_") and not n.startswith("__") and t != m and (m, t, n) not in ALLOWED_PRIVATE]
    assert not bad, bad


def test_studies_import_public_names_only():
    """A study (experiments/studies/) uses the harness and the library through their public names only."""
    bad = []
    for path in (EXPERIMENTS / "studies").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in ("experiments", "torchmm"):
                bad += [(path.name, node.module, a.name) for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
                bad += [(path.name, node.module, "") for part in node.module.split(".")
                        if part.startswith("_") and not part.startswith("__")]
    assert not bad, bad


# -- the one seam for speed (issue 31, goal 3) --------------------------------------------------------
def _concrete_filter_classes() -> set[str]:
    """Names of torchmm's concrete filter classes: every subclass of ``Filter`` that torchmm exports,
    except the abstract bases a combinator is written against."""
    import inspect

    import torchmm.filters
    import torchmm.fusion
    import torchmm.multimodel
    from torchmm.filters import Filter

    abstract = {"Filter", "MultipleModelFilter"}
    names = set()
    for module in (torchmm, torchmm.filters, torchmm.multimodel, torchmm.fusion):
        for name, value in vars(module).items():
            if inspect.isclass(value) and issubclass(value, Filter) and name not in abstract:
                names.add(name)
    return names


def _class_tests(tree: ast.AST) -> list[tuple[int, str]]:
    """``(line, name)`` of every name in ``isinstance(x, C)``, ``issubclass(x, C)`` (also in tuples) and
    in ``is / is not / in / not in / == / !=`` comparisons (``type(x) is C``, ``kind in (C, D)``)."""
    found = []

    def names(node):
        if isinstance(node, ast.Name):
            yield node.id
        elif isinstance(node, ast.Attribute):
            yield node.attr
        elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            for item in node.elts:
                yield from names(item)

    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id in ("isinstance", "issubclass") and len(node.args) == 2):
            found += [(node.lineno, n) for n in names(node.args[1])]
        elif isinstance(node, ast.Compare) and all(
                isinstance(op, (ast.Is, ast.IsNot, ast.In, ast.NotIn, ast.Eq, ast.NotEq)) for op in node.ops):
            # type(x) is C, kind not in (C, D), ...: any class compared by identity or membership
            for operand in (node.left, *node.comparators):
                found += [(node.lineno, n) for n in names(operand)]
    return found


def test_the_multiple_model_engine_tests_no_concrete_filter_class():
    """multimodel/ finds speed (and everything else) through capabilities and the kernel seam
    (torchmm.kernels: a filter joins a kernel family, a kernel registers), never by testing for a
    concrete filter class such as KalmanFilter, IMM or GPB1 (docs/architecture.md, "Kernels")."""
    concrete = _concrete_filter_classes()
    assert {"KalmanFilter", "IMM", "GPB1", "ExtendedKalmanFilter"} <= concrete  # the check sees them
    bad = []
    for path in sorted((ROOT / "multimodel").rglob("*.py")):
        for line, name in _class_tests(ast.parse(path.read_text())):
            if name in concrete:
                bad.append(f"{path.relative_to(ROOT.parent)}:{line}: {name}")
    assert not bad, bad


def test_smooth_names_no_filter_class():
    """torchmm.smooth runs the backward pass a filter names (``Filter.smoother``: "rts", "unscented",
    "particles", "modes"; issue 47), never testing for a filter class, and imports none at run time."""
    concrete = _concrete_filter_classes() | {"MultipleModelFilter"}
    for file in ("smooth.py", "two_filter.py"):  # (the two-filter smoother: split from smooth.py)
        tree = ast.parse((ROOT / file).read_text())
        bad = [f"{file}:{line}: {name}" for line, name in _class_tests(tree) if name in concrete]
        assert not bad, bad
        runtime = [a.name for node in tree.body if isinstance(node, ast.ImportFrom) for a in node.names]
        assert not set(runtime) & concrete, sorted(set(runtime) & concrete)


def test_the_class_test_finder_finds_class_tests():
    source = ("isinstance(f, (KalmanFilter, Foo))\nif type(f) is not IMM: pass\nkind in (GPB1,)\n"
              "issubclass(k, torchmm.UnscentedKalmanFilter)\nx < StaticMM\n")
    found = [n for _, n in _class_tests(ast.parse(source))]
    assert found == ["KalmanFilter", "Foo", "IMM", "kind", "GPB1", "UnscentedKalmanFilter"], found
    # the engine before the seam (issue 31) fails the check
    old = "kind = type(self)\nif kind not in (IMM, GPB1):\n    pass\nif type(kf) is not KalmanFilter:\n    pass\n"
    assert {"IMM", "GPB1", "KalmanFilter"} <= {n for _, n in _class_tests(ast.parse(old))}


# -- split modules keep the paths configs, docs and users name (issue 47) ------------------------------------
MOVED = [  # (old path, new home): the same object through both
    ("torchmm.filters.variational.SkewTVBFilter", "torchmm.filters.skew_t.SkewTVBFilter"),
    ("torchmm.filters.variational.SkewTIWVBFilter", "torchmm.filters.skew_t.SkewTIWVBFilter"),
    ("torchmm.filters.variational.gamma_kl", "torchmm.filters.vb_common.gamma_kl"),
    ("torchmm.filters.variational.wishart_kl", "torchmm.filters.vb_common.wishart_kl"),
    ("torchmm.filters.particle.noise_factor", "torchmm.filters.particle_ops.noise_factor"),
    ("torchmm.filters.particle.propagate_particles", "torchmm.filters.particle_ops.propagate_particles"),
    ("torchmm.multimodel.particle.ParticleMixing", "torchmm.multimodel.particle_mixing.ParticleMixing"),
    ("torchmm.multimodel.particle.mixing_indices", "torchmm.multimodel.particle_mixing.mixing_indices"),
    ("torchmm.multimodel.policies.ChallengeMatch", "torchmm.multimodel.challenge.ChallengeMatch"),
    ("torchmm.multimodel.mevsmm.ChallengeMatch", "torchmm.multimodel.challenge.ChallengeMatch"),
    ("torchmm.multimodel.GPB2", "torchmm.multimodel.gpb2.GPB2"),
    ("torchmm.fusion.cross_covariances", "torchmm.fusion.cross.cross_covariances"),
    ("experiments.scenarios.system", "experiments.scenarios_system.system"),
    ("experiments.scenarios.SystemScenario", "experiments.scenarios_system.SystemScenario"),
    ("experiments.datafile.DataFileError", "experiments.datafile_io.DataFileError"),
    ("experiments.studies.tracking.estimators", "experiments.studies.tracking_estimators.estimators"),
]


def _object(path: str):
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("old, new", MOVED, ids=[old for old, _ in MOVED])
def test_a_split_keeps_the_old_path(old, new):
    """A config's ``_target_``, the docs and users' imports name the old path: it is the moved object itself."""
    assert _object(old) is _object(new)
