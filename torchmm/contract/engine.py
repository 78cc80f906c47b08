"""The entry-point decorator of the contract (:mod:`torchmm.contract`): :func:`entry_point` binds a call,
checks each argument the caller passed against its declared kind (:mod:`torchmm.contract.kinds`) and names
the parameter in every error; :data:`REGISTRY` keeps every entry point for the test suite's enumeration."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from torchmm.contract.kinds import Kind

__all__ = ["REGISTRY", "EntryPoint", "entry_point", "registered", "spec_of", "unchecked"]

#: Every registered entry point, by ``module.qualname`` of the function.
REGISTRY: dict[str, EntryPoint] = {}

_EMPTY = inspect.Parameter.empty


# -- the decorator ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class EntryPoint:
    """A registered entry point: its function and the kind of each parameter."""

    qualname: str
    function: Callable
    kinds: dict
    signature: inspect.Signature


def unchecked(entry: Callable) -> Callable:
    """The function behind an entry point, without its checks: for a library caller that checked
    its values at its own entry point already, where a second check would read values on the host
    again (a synchronisation on a GPU; e.g. ``gospa`` calling ``linear_assignment``). Shape and
    dimension checks inside the function still run."""
    spec = getattr(entry, "__entry_point__", None)
    if spec is None:
        raise TypeError(f"unchecked: {entry!r} is not an entry point")
    return spec.function


def entry_point(**kinds: Kind) -> Callable[[Callable], Callable]:
    """Declare ``fn`` an entry point and the kind of each of its parameters.

    Every parameter of the signature (except ``self``/``cls`` and ``*args``/``**kwargs``) must be
    declared: an undeclared one is a ``TypeError`` at import (a new parameter is checked by
    construction). Arguments the caller passes are checked against their kinds before ``fn`` runs;
    defaults are not. Decorate ``__init__`` for a class, the function for a function (under
    ``@classmethod``/``@staticmethod``).
    """
    for name, kind in kinds.items():
        if not isinstance(kind, Kind):
            raise TypeError(f"entry_point: the kind of {name!r} must be a Kind, got {kind!r}")

    def decorate(fn: Callable) -> Callable:
        signature = inspect.signature(fn)
        names = [p.name for p in signature.parameters.values()
                 if p.name not in ("self", "cls") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        missing = [n for n in names if n not in kinds]
        unknown = [n for n in kinds if n not in names]
        if missing or unknown:
            raise TypeError(f"entry_point({fn.__module__}.{fn.__qualname__}): "
                            + (f"no kind declared for {missing}" if missing else "")
                            + ("; " if missing and unknown else "")
                            + (f"{unknown} are not parameters" if unknown else ""))
        checked = tuple((n, k) for n, k in kinds.items() if type(k).check is not Kind.check
                        and getattr(k, "enforce", True))
        bind = _binder(signature)

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            arguments, bound = bind(args, kwargs), None
            if arguments is None:  # (variadic or positional-only parameters, or an error to name)
                try:
                    bound = signature.bind(*args, **kwargs)
                except TypeError:  # a missing, unknown or extra argument: named, as every other error
                    raise TypeError(_bind_error(fn, signature, args, kwargs)) from None
                arguments = bound.arguments  # (the mapping bound.args and bound.kwargs are made from)
            for name, kind in checked:
                if name in arguments:
                    value = arguments[name]
                    new = kind.check(value, name)
                    if new is not value:
                        arguments[name] = new
            return fn(**arguments) if bound is None else fn(*bound.args, **bound.kwargs)

        spec = EntryPoint(f"{fn.__module__}.{fn.__qualname__}", fn, dict(kinds), signature)
        wrapper.__entry_point__ = spec
        REGISTRY[spec.qualname] = spec
        return wrapper

    return decorate


def _binder(signature: inspect.Signature) -> Callable[[tuple, dict], dict | None]:
    """``signature.bind(*args, **kwargs).arguments`` without ``inspect``'s general machinery (ten
    microseconds a call: the one-shot call's cost, issue 47), for a signature of plain parameters (no
    ``*args``, ``**kwargs`` or positional-only ones): the passed arguments by name (the checks run in the
    kinds' order, the call passes them by keyword), or None where the call does not bind (the caller then
    binds as ``inspect`` does, to name the error) or the signature is not plain."""
    params = list(signature.parameters.values())
    if any(p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD, p.POSITIONAL_ONLY) for p in params):
        return lambda args, kwargs: None
    positional = tuple(p.name for p in params if p.kind is p.POSITIONAL_OR_KEYWORD)
    names = frozenset(p.name for p in params)
    required = tuple(p.name for p in params if p.default is p.empty)

    def bind(args: tuple, kwargs: dict) -> dict | None:
        if len(args) > len(positional):
            return None
        arguments = dict(zip(positional, args))
        for key, value in kwargs.items():
            if key in arguments or key not in names:
                return None
            arguments[key] = value
        for name in required:
            if name not in arguments:
                return None
        return arguments

    return bind


def _called(fn: Callable, signature: inspect.Signature, args: tuple, kwargs: dict) -> str:
    """What the user called: the class for a constructor (the instance's, for an inherited one), the
    class and method for a method, the function's name otherwise."""
    first = next(iter(signature.parameters), None)
    owner = None
    if first in ("self", "cls"):
        this = args[0] if args else kwargs.get(first)
        if this is not None:
            owner = this.__name__ if isinstance(this, type) else type(this).__name__
    if owner is None:
        return fn.__qualname__.removesuffix(".__init__")
    return owner if fn.__name__ == "__init__" else f"{owner}.{fn.__name__}"


def _bind_error(fn: Callable, signature: inspect.Signature, args: tuple, kwargs: dict) -> str:
    """The message of a call that ``signature`` cannot bind, starting with the argument's name (a
    missing or unknown one, one given twice) or, for too many positional arguments, the function's."""
    import difflib

    where = _called(fn, signature, args, kwargs)
    params = signature.parameters
    named = [p for p in params.values() if p.name not in ("self", "cls")
             and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    names = [p.name for p in named]
    variadic_keywords = any(p.kind is p.VAR_KEYWORD for p in params.values())
    for key in kwargs:
        if key not in params and not variadic_keywords or \
                key in params and params[key].kind is params[key].POSITIONAL_ONLY:
            close = difflib.get_close_matches(key, names, n=1)
            hint = f"did you mean {close[0]}? " if close else ""
            return f"{key}: not an argument of {where} ({hint}arguments: {', '.join(names)})"
    positional = [p for p in params.values() if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(args) > len(positional) and not any(p.kind is p.VAR_POSITIONAL for p in params.values()):
        shown = [p.name for p in positional if p.name not in ("self", "cls")]
        offset = len(positional) - len(shown)  # self / cls
        keyword_only = [p.name for p in named if p.kind is p.KEYWORD_ONLY]
        plural = "" if len(shown) == 1 else "s"
        return (f"{where}: takes {len(shown)} positional argument{plural} ({', '.join(shown) or 'none'}), got "
                f"{len(args) - offset}" + (f"; {', '.join(keyword_only)} {'is' if len(keyword_only) == 1 else 'are'} "
                                           "keyword-only" if keyword_only else ""))
    for p in positional[:len(args)]:
        if p.name in kwargs and p.kind is not p.POSITIONAL_ONLY:
            return f"{p.name}: given twice (by position and by keyword) to {where}"
    try:
        given = signature.bind_partial(*args, **kwargs).arguments
    except TypeError as err:
        return f"{where}: {err}"
    missing = [p.name for p in params.values() if p.name not in given and p.default is p.empty
               and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    if missing:
        first, rest = missing[0], missing[1:]
        also = f"; {', '.join(rest)} {'is' if len(rest) == 1 else 'are'} missing too" if rest else ""
        return f"{first}: missing (a required argument of {where}{also})"
    try:
        signature.bind(*args, **kwargs)
    except TypeError as err:
        return f"{where}: {err}"
    return f"{where}: the arguments do not fit its signature {signature}"


def spec_of(obj: Any) -> EntryPoint | None:
    """The entry point behind a public object: a function's own, a class's ``__init__``'s."""
    if isinstance(obj, type):
        init = obj.__dict__.get("__init__")
        if init is None:  # inherited: the nearest registered base constructor
            for base in obj.__mro__[1:]:
                init = base.__dict__.get("__init__")
                if init is not None:
                    break
        return getattr(init, "__entry_point__", None)
    return getattr(obj, "__entry_point__", None)


def registered() -> dict[str, EntryPoint]:
    """Every registered entry point (a copy)."""
    return dict(REGISTRY)
