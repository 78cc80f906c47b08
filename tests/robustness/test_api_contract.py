"""The whole public API under the entry-point contract (torchmm/contract/, docs/robustness.md).

1. **Enumeration.** Every callable in ``torchmm.__all__`` and in every subpackage's ``__all__`` is
   a registered entry point (``@entry_point`` on the function or the class's ``__init__``) or is
   listed in :data:`~tests.robustness.api_examples.NOT_ENTRY_POINTS` with the reason. A new public
   function is red here until it is one or the other.
2. **Examples.** Every entry point has a valid example call
   (:data:`~tests.robustness.api_examples.EXAMPLES`), which runs.
3. **Invalid inputs, by kind.** For every declared parameter, every invalid input its kind lists
   (wrong types, non-finite values, non-PSD matrices, non-stochastic rows, zero and empty sizes,
   wrong shapes and dtypes, a class for an instance) replaces the example's argument, and the call
   must raise ``TypeError`` or ``ValueError`` whose message starts with the parameter's name.
4. **Valid edges, by kind.** For every declared parameter, every equivalent its kind lists
   (:meth:`~torchmm.contract.Kind.equivalents`: a padded set of size 0, :class:`~torchmm.contract.Sets`)
   replaces the example's argument and must be accepted; where it names a reference (the set of the
   same batch whose every element is missing), the two calls give the same results where their
   shapes agree (the empty set's result has no column for the missing elements).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import re
import warnings

import pytest
import torch

from torchmm import contract
from tests.robustness.api_examples import EXAMPLES, NOT_ENTRY_POINTS, Call

SUBPACKAGES = ["analysis", "assignment", "association", "beliefs", "kernels", "kernels.linear", "kernels.particle",
               "filters", "fusion", "learn", "metrics", "models", "multimodel", "simulate", "parallel"]


def public_objects() -> dict[str, object]:
    """Every public callable, by the ``module.qualname`` where it is defined (deduplicated)."""
    out = {}
    for module_name in ["torchmm"] + [f"torchmm.{m}" for m in SUBPACKAGES]:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            obj = getattr(module, name)
            if inspect.ismodule(obj) or not callable(obj):
                continue
            out[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return out


PUBLIC = public_objects()


def _key(obj) -> str:
    return f"{obj.__module__}.{obj.__qualname__}"


def entry_keys() -> list[str]:
    """The keys of every entry point that needs an example: public classes and functions that are
    entry points, and every registered method (``initial_belief``, ``create``, ...)."""
    keys = {k for k, obj in PUBLIC.items() if k not in NOT_ENTRY_POINTS}
    for qualname in contract.registered():
        if not qualname.endswith(".__init__"):
            keys.add(qualname)
    return sorted(keys)


@pytest.mark.parametrize("key", sorted(PUBLIC))
def test_every_public_callable_is_an_entry_point_or_exempt(key):
    obj = PUBLIC[key]
    if key in NOT_ENTRY_POINTS:
        assert contract.spec_of(obj) is None or isinstance(obj, type), \
            f"{key} is registered as an entry point but listed in NOT_ENTRY_POINTS"
        assert NOT_ENTRY_POINTS[key].strip(), f"{key}: give the reason it is not an entry point"
        return
    assert contract.spec_of(obj) is not None, (
        f"{key} is public but not an entry point: declare its parameters with @entry_point(...) "
        "(torchmm/contract/) or list it in NOT_ENTRY_POINTS with the reason")


def test_exempt_names_exist():
    stale = sorted(set(NOT_ENTRY_POINTS) - set(PUBLIC))
    assert not stale, f"NOT_ENTRY_POINTS names no public object: {stale}"


def test_every_entry_point_has_an_example():
    missing = [k for k in entry_keys() if k not in EXAMPLES]
    assert not missing, f"entry points without a valid example in tests/robustness/api_examples.py: {missing}"
    stale = sorted(set(EXAMPLES) - set(entry_keys()))
    assert not stale, f"examples of no entry point: {stale}"


def _spec(call: Call):
    spec = (contract.spec_of(call.fn) if isinstance(call.fn, type)
            else getattr(call.fn, "__entry_point__", None))
    assert spec is not None, f"{call.fn!r} is not an entry point"
    return spec


def _bind(call: Call):
    signature = inspect.signature(call.fn)
    bound = signature.bind(*call.args, **call.kwargs)
    return signature, bound


@pytest.mark.parametrize("key", sorted(EXAMPLES))
def test_example_runs(key):
    call = EXAMPLES[key]()
    _bind(call)
    call.fn(*call.args, **call.kwargs)


def _parameters():
    out = []
    for key in sorted(EXAMPLES):
        obj = PUBLIC.get(key)
        spec = contract.spec_of(obj) if obj is not None else contract.registered().get(key)
        if spec is None:
            continue  # reported by test_every_entry_point_has_an_example
        for name, kind in spec.kinds.items():
            out.append(pytest.param(key, name, id=f"{key.removeprefix('torchmm.')}-{name}"))
    return out


@pytest.mark.parametrize("key, name", _parameters())
def test_invalid_inputs_raise_naming_the_parameter(key, name):
    call = EXAMPLES[key]()
    spec = _spec(call)
    kind = spec.kinds[name]
    signature, bound = _bind(call)
    parameter = signature.parameters[name]
    valid = bound.arguments.get(name, parameter.default)
    if valid is inspect.Parameter.empty:
        valid = None
    # a validator's own ``name=`` parameter (Text(label=True)) is the label its errors carry
    label = name
    for other, other_kind in spec.kinds.items():
        if other != name and getattr(other_kind, "label", False):
            label = bound.arguments.get(other, signature.parameters[other].default)
    failures = []
    for invalid in kind.invalid(valid):
        arguments = dict(bound.arguments)
        arguments[name] = invalid.value
        trial = signature.bind_partial()
        trial.arguments.update(arguments)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                call.fn(*trial.args, **trial.kwargs)
        except invalid.raises as err:
            message = str(err)
            if not re.match(rf"{re.escape(label)}\b", message):
                failures.append(f"{invalid.cls} {_show(invalid.value)}: {type(err).__name__} does not start "
                                f"with {label!r}: {message[:200]!r}")
        except Exception as err:  # noqa: BLE001 - a raw error is a failure of the contract
            failures.append(f"{invalid.cls} {_show(invalid.value)}: raw {type(err).__name__}: "
                            f"{str(err)[:200]!r}")
        else:
            failures.append(f"{invalid.cls} {_show(invalid.value)}: accepted silently")
    assert not failures, f"{key}({name}=...):\n" + "\n".join(failures)


def _show(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"tensor{tuple(value.shape)} {value.dtype}"
    text = repr(value)
    return text if len(text) < 60 else text[:57] + "..."


def _equivalent_parameters():
    out = []
    for key in sorted(EXAMPLES):
        obj = PUBLIC.get(key)
        spec = contract.spec_of(obj) if obj is not None else contract.registered().get(key)
        if spec is None:
            continue
        for name, kind in spec.kinds.items():
            if type(kind).equivalents is not contract.Kind.equivalents:
                out.append(pytest.param(key, name, id=f"{key.removeprefix('torchmm.')}-{name}"))
    return out


def _leaves(result, path="result"):
    """The tensors of a result (tuples, lists, dicts, dataclasses, NamedTuples), by path."""
    if isinstance(result, torch.Tensor):
        return [(path, result)]
    if isinstance(result, dict):
        return [leaf for k in result for leaf in _leaves(result[k], f"{path}[{k!r}]")]
    if isinstance(result, (tuple, list)):
        return [leaf for i, v in enumerate(result) for leaf in _leaves(v, f"{path}[{i}]")]
    if dataclasses.is_dataclass(result):
        return [leaf for f in dataclasses.fields(result) for leaf in _leaves(getattr(result, f.name), f"{path}.{f.name}")]
    return []


@pytest.mark.parametrize("key, name", _equivalent_parameters())
def test_valid_edges_are_accepted_and_give_the_reference_result(key, name):
    call = EXAMPLES[key]()
    spec = _spec(call)
    signature, bound = _bind(call)
    valid = bound.arguments.get(name, signature.parameters[name].default)
    kind = spec.kinds[name]
    trials = kind.equivalents(valid)
    assert trials, f"{key}({name}=...): the example's argument gives its kind no edge to try"
    mask = getattr(kind, "mask", None)  # the set's presence flags, emptied with it
    for edge in trials:
        results = []
        for value in (edge.value, edge.reference):
            if value is None:
                continue
            arguments = {**bound.arguments, name: value}
            if mask is not None and value is edge.value and arguments.get(mask) is not None:
                arguments[mask] = arguments[mask].narrow(-1, 0, 0)
            trial = signature.bind_partial()
            trial.arguments.update(arguments)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                results.append(call.fn(*trial.args, **trial.kwargs))
        if len(results) < 2:
            continue
        got, want = _leaves(results[0]), _leaves(results[1])
        assert [p for p, _ in got] == [p for p, _ in want]
        for (path, a), (_, b) in zip(got, want):
            if a.dim() != b.dim():
                continue
            common = [min(x, y) for x, y in zip(a.shape, b.shape)]
            for axis, size in enumerate(common):
                a, b = a.narrow(axis, 0, size), b.narrow(axis, 0, size)
            torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True,
                                       msg=lambda m, path=path: f"{key}({name}={edge.cls}): {path}: {m}")


# -- the call itself: a missing, unknown or extra argument names it (the contract's bind) ------------
def _required_parameters():
    out = []
    for key in sorted(EXAMPLES):
        call = EXAMPLES[key]()
        signature = inspect.signature(call.fn)
        for p in signature.parameters.values():
            if p.name in ("self", "cls") or p.default is not p.empty or \
                    p.kind not in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
                continue
            out.append(pytest.param(key, p.name, id=f"{key.removeprefix('torchmm.')}-{p.name}"))
    return out


@pytest.mark.parametrize("key, name", _required_parameters())
def test_a_missing_required_argument_is_named(key, name):
    """Every required parameter of every entry point, left out of its valid example: a ``TypeError``
    starting with the parameter's name (before: Signature.bind's ``missing a required argument: ...``)."""
    call = EXAMPLES[key]()
    signature, bound = _bind(call)
    trial = signature.bind_partial()
    trial.arguments.update({k: v for k, v in bound.arguments.items() if k != name})
    with pytest.raises(TypeError, match=rf"^{re.escape(name)}: missing \(a required argument of \w[\w.]*\)"):
        call.fn(*trial.args, **trial.kwargs)


@pytest.mark.parametrize("key", sorted(EXAMPLES))
def test_an_unknown_keyword_is_named(key):
    call = EXAMPLES[key]()
    if any(p.kind is p.VAR_KEYWORD for p in inspect.signature(call.fn).parameters.values()):
        pytest.skip("takes **kwargs")
    with pytest.raises(TypeError, match=r"^no_such_argument: not an argument of \w[\w.]* \(arguments: "):
        call.fn(*call.args, **call.kwargs, no_such_argument=1)


def test_bind_errors_name_the_argument_or_the_function():
    from torchmm import GPB1, GaussianBelief, KalmanFilter
    from torchmm.association import PDA
    from torchmm.models import ConstantVelocity, PositionMeasurement

    kf = KalmanFilter(ConstantVelocity(2, q=0.5), PositionMeasurement(4, [0, 2], 1.0))
    with pytest.raises(TypeError, match=r"^detection_probability: missing \(a required argument of PDA\)$"):
        PDA(kf, clutter_density=0.01)
    with pytest.raises(TypeError, match=r"^detection_probability: missing \(a required argument of PDA; "
                                        r"clutter_density is missing too\)$"):
        PDA(kf)
    with pytest.raises(TypeError, match=r"^foo: not an argument of PDA \(arguments: filter, detection_probability, "
                                        r"clutter_density, gate_probability\)$"):
        PDA(kf, detection_probability=0.9, clutter_density=0.01, foo=1)
    with pytest.raises(TypeError, match=r"^gate_probabilty: not an argument of PDA \(did you mean "
                                        r"gate_probability\?"):
        PDA(kf, detection_probability=0.9, clutter_density=0.01, gate_probabilty=0.9)
    with pytest.raises(TypeError, match=r"^PDA: takes 1 positional argument \(filter\), got 3; "
                                        r"detection_probability, clutter_density, gate_probability are keyword-only"):
        PDA(kf, 0.9, 0.01)
    with pytest.raises(TypeError, match=r"^filter: given twice \(by position and by keyword\) to PDA$"):
        PDA(kf, filter=kf, detection_probability=0.9, clutter_density=0.01)
    # an inherited constructor and a method: named by the class the user called
    with pytest.raises(TypeError, match=r"^transition: missing \(a required argument of GPB1\)$"):
        GPB1(kf)
    gpb1 = GPB1([kf, kf], torch.eye(2))
    with pytest.raises(TypeError, match=r"^belief: missing \(a required argument of GPB1.initial_belief\)$"):
        gpb1.initial_belief()
    with pytest.raises(TypeError, match=r"^GaussianBelief.create: takes 2 positional arguments "):
        GaussianBelief.create(torch.zeros(2), torch.eye(2), 1, 2)


def test_the_fast_binder_binds_as_inspect_does():
    """The entry points' binder (torchmm.contract.engine._binder, issue 47: the one-shot call's cost) gives
    ``inspect.Signature.bind``'s arguments for every call that binds, and None (inspect then names the
    error) for every call that does not, or for signatures it does not handle."""
    import inspect
    import itertools

    from torchmm.contract.engine import _binder

    def plain(self, a, b=1, *, c, d=2):
        pass

    def only(a, /, b):
        pass

    def variadic(a, *rest, **more):
        pass

    calls = [((), {}), ((0,), {}), ((0, 1), {}), ((0, 1, 2), {}), ((0, 1, 2, 3), {}), ((0,), {"a": 1, "c": 2}),
             ((0, 1), {"c": 3}), ((0, 1), {"b": 2, "c": 3}), ((0, 1, 2), {"c": 3, "d": 4}), ((0, 1), {"e": 3, "c": 1}),
             ((0,), {"a": 1, "b": 2, "c": 3}), ((), {"self": 0, "a": 1, "c": 2})]
    for fn, (args, kwargs) in itertools.product((plain, only, variadic), calls):
        sig = inspect.signature(fn)
        try:
            want = dict(sig.bind(*args, **kwargs).arguments)
        except TypeError:
            want = None
        got = _binder(sig)(args, kwargs)
        if fn is plain:
            assert got == want, (args, kwargs, got, want)
        else:
            assert got is None  # (inspect binds these itself)
