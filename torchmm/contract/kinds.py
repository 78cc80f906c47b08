"""The parameter kinds of the entry-point contract (:mod:`torchmm.contract`): what each public parameter
is (an integer, a flag, a covariance, a transition, a belief, ...), how an argument is checked against it,
and which invalid inputs the test suite tries for it (:meth:`Kind.invalid`). Split from the decorator that
applies them (:mod:`torchmm.contract.engine`, issue 47); the kinds of tensors and beliefs are in
:mod:`torchmm.contract.tensor_kinds`."""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchmm.validation import as_float, as_int

__all__ = [
    "Choice",
    "DType",
    "Device",
    "Equivalent",
    "FilePath",
    "Flag",
    "Gen",
    "Indices",
    "Int",
    "Invalid",
    "Kind",
    "Of",
    "Real",
    "Shape",
    "Text",
    "Unchecked",
]



@dataclass(frozen=True)
class Invalid:
    """One invalid input for a parameter: its class (``"type"``, ``"non-finite"``, ...), the value,
    and the exception types an entry point may raise for it."""

    cls: str
    value: Any
    raises: tuple = (TypeError, ValueError)



@dataclass(frozen=True)
class Equivalent:
    """A valid edge input that must give the result of another input: ``value`` (e.g. a set of size
    0) and ``reference`` (e.g. a set whose rows are all missing); ``reference=None``: ``value`` must
    only be accepted (no error). The contract test calls the function with both and compares the
    results where their shapes agree."""

    cls: str
    value: Any
    reference: Any = None



class Kind:
    """The kind of a parameter: ``check`` runs at entry, ``invalid`` lists what the tests try."""

    optional: bool = False

    def check(self, value: Any, name: str) -> Any:
        """Return ``value`` (possibly converted) or raise naming ``name``."""
        return value

    def invalid(self, valid: Any) -> list[Invalid]:
        """Invalid inputs, built from a valid one (``valid`` may be a default)."""
        return []

    def equivalents(self, valid: Any) -> list[Equivalent]:
        """Valid edge inputs and what they must equal (:class:`Equivalent`), built from a valid one."""
        return []

    def _none(self, value, name) -> bool:
        if value is None:
            if self.optional:
                return True
            raise TypeError(f"{name}: expected {self.describe()}, got None")
        return False

    def describe(self) -> str:
        return type(self).__name__



class Unchecked(Kind):
    """A parameter that no check applies to (a callable, a free-form label); ``reason`` says why."""

    def __init__(self, reason: str):
        self.reason = reason



class Int(Kind):
    """An integer (``int``, NumPy integer, integral 0-d tensor; never ``bool`` or ``2.5``).
    ``check=False``: the function checks it (the kind only declares what the tests try)."""

    def __init__(self, minimum: int | None = None, *, optional: bool = False, check: bool = True):
        self.minimum, self.optional, self.enforce = minimum, optional, check

    def describe(self):
        return "an integer"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        return as_int(value, name, minimum=self.minimum)

    def invalid(self, valid):
        out = [Invalid("type", 2.5), Invalid("type", True), Invalid("type", "3")]
        if self.minimum is not None:
            out.append(Invalid("range", self.minimum - 1))
        return out



class Real(Kind):
    """A finite real number, optionally bounded (``positive``: strictly above 0)."""

    def __init__(self, minimum: float | None = None, maximum: float | None = None, *, positive: bool = False,
                 optional: bool = False, tensor: bool = False):
        self.minimum, self.maximum, self.positive, self.optional = minimum, maximum, positive, optional
        self.tensor = tensor  # a tensor argument is kept as it is (autograd), only checked

    def describe(self):
        return "a number"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, Tensor):
            if value.numel() != 1:
                if not self.tensor:
                    raise ValueError(f"{name}: expected a number, got a tensor of shape {tuple(value.shape)}")
                return value
            as_float(value, name, minimum=self.minimum, maximum=self.maximum, positive=self.positive)
            return value
        return as_float(value, name, minimum=self.minimum, maximum=self.maximum, positive=self.positive)

    def invalid(self, valid):
        out = [Invalid("type", "1"), Invalid("non-finite", math.nan), Invalid("non-finite", math.inf)]
        if self.positive:
            out.append(Invalid("range", 0.0))
        if self.minimum is not None:
            out.append(Invalid("range", self.minimum - 1.0))
        if self.maximum is not None:
            out.append(Invalid("range", self.maximum + 1.0))
        return out



class Flag(Kind):
    """A ``bool`` (NumPy's too); ``'no'``, ``1`` or ``None`` are ``TypeError``."""

    def __init__(self, *, optional: bool = False):
        self.optional = optional

    def describe(self):
        return "True or False"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, bool):
            return value
        if type(value).__name__ == "bool_":  # numpy.bool_
            return bool(value)
        raise TypeError(f"{name}: expected {'None, ' if self.optional else ''}True or False, got {value!r}")

    def invalid(self, valid):
        return [Invalid("type", "no"), Invalid("type", 1)]



class Choice(Kind):
    """One of a set of strings. ``check=False``: the function checks it (the options depend on
    another argument)."""

    def __init__(self, *choices: str, optional: bool = False, check: bool = True):
        self.choices, self.optional, self.enforce = choices, optional, check

    def describe(self):
        return f"one of {list(self.choices)}"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if not isinstance(value, str) or value not in self.choices:
            raise ValueError(f"{name}: expected one of {list(self.choices)}, got {value!r}")
        return value

    def invalid(self, valid):
        return [Invalid("value", "no-such-option"), Invalid("type", 1)]



class Text(Kind):
    """A string (an attribute name, a label). ``label``: the name that the function's errors carry
    in place of the other parameters' own (a validator's ``name=``)."""

    def __init__(self, *, optional: bool = False, label: bool = False):
        self.optional, self.label = optional, label

    def describe(self):
        return "a string"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if not isinstance(value, str):
            raise TypeError(f"{name}: expected a string, got {value!r}")
        return value

    def invalid(self, valid):
        return [Invalid("type", 1)]



class Gen(Kind):
    """A :class:`torch.Generator` (``None`` allowed when ``optional``). Its device is checked
    against the data where the data are known (``run_filter``)."""

    def __init__(self, *, optional: bool = True):
        self.optional = optional

    def describe(self):
        return "a torch.Generator"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if not isinstance(value, torch.Generator):
            hint = " (seed one: torch.Generator().manual_seed(seed))" if isinstance(value, (int, str)) else ""
            raise TypeError(f"{name}: expected a torch.Generator, got {value!r}{hint}")
        return value

    def invalid(self, valid):
        return [Invalid("type", "seed"), Invalid("type", 0), Invalid("type", torch.Generator)]



class DType(Kind):
    """A floating :class:`torch.dtype` (``None`` allowed when ``optional``: the default dtype)."""

    def __init__(self, *, optional: bool = True, strings: bool = False):
        self.optional, self.strings = optional, strings

    def describe(self):
        return "a floating torch.dtype"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if self.strings and isinstance(value, str) and isinstance(getattr(torch, value, None), torch.dtype):
            value = getattr(torch, value)
        if not isinstance(value, torch.dtype):
            raise TypeError(f"{name}: expected a torch.dtype such as torch.float64, got {value!r}")
        if not value.is_floating_point:
            raise TypeError(f"{name}: expected a floating dtype, got {value}")
        return value

    def invalid(self, valid):
        return [Invalid("type", "float-64"), Invalid("type", 64), Invalid("dtype", torch.int64)]



class Device(Kind):
    """A :class:`torch.device` or its name (``"cpu"``, ``"cuda:0"``)."""

    def __init__(self, *, optional: bool = True):
        self.optional = optional

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, torch.device):
            return value
        if isinstance(value, (str, int)) and not isinstance(value, bool):
            try:
                return torch.device(value)
            except (RuntimeError, TypeError, ValueError) as err:
                raise ValueError(f"{name}: not a device ({err})") from None
        raise TypeError(f"{name}: expected a torch.device or its name, got {value!r}")

    def invalid(self, valid):
        return [Invalid("value", "no-such-device"), Invalid("type", 1.5)]



class Of(Kind):
    """An instance of ``types``, or an object with the ``methods`` (duck typing). A class given for
    an instance (``policy=FixedSet``) is a ``TypeError`` that says so."""

    def __init__(self, types: type | tuple = (), *, methods: Sequence[str] = (), what: str = "",
                 optional: bool = False, callable_ok: bool = False, check: bool = True):
        self.types = types if isinstance(types, tuple) else (types,)
        self.methods, self.optional, self.callable_ok = tuple(methods), optional, callable_ok
        self.enforce = check  # False: the function checks it (the argument's meaning depends on another)
        self.what = what or " or ".join(t.__name__ for t in self.types) or "an object with " + \
            ", ".join(self.methods)

    def describe(self):
        return self.what

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if isinstance(value, type):
            raise TypeError(f"{name}: expected an instance ({self.what}), got the class {value.__name__}; "
                            f"create one: {value.__name__}(...)")
        if self.types and isinstance(value, self.types):
            return value
        if self.methods and all(callable(getattr(value, m, None)) for m in self.methods):
            return value
        if self.callable_ok and callable(value):
            return value
        raise TypeError(f"{name}: expected {self.what}, got {type(value).__name__}")

    def invalid(self, valid):
        out = [Invalid("type", "not-an-object")]
        if valid is not None and not isinstance(valid, type):
            out.append(Invalid("type", type(valid)))  # the class for an instance
        return out



class Indices(Kind):
    """A sequence of integers (state or model indices), non-empty unless ``empty``; each index at
    least ``minimum``."""

    def __init__(self, *, empty: bool = False, minimum: int = 0, optional: bool = False):
        self.empty, self.minimum, self.optional = empty, minimum, optional

    def describe(self):
        return "a sequence of integers"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, Tensor):
            if value.is_floating_point() or value.dim() != 1:
                raise TypeError(f"{name}: expected a sequence of integers, got a tensor of dtype "
                                f"{value.dtype} and shape {tuple(value.shape)}")
            value = value.tolist()
        if (isinstance(value, (str, bytes))
                or not isinstance(value, Sequence) and not hasattr(value, "__iter__")):
            raise TypeError(f"{name}: expected a sequence of integers, got {value!r}")
        items = list(value)
        for i in items:
            if isinstance(i, bool) or not isinstance(i, numbers.Integral):
                raise TypeError(f"{name}: expected a sequence of integers, got the entry {i!r}")
            if i < self.minimum:
                raise ValueError(f"{name}: entries must be >= {self.minimum}, got {int(i)}")
        if not items and not self.empty:
            raise ValueError(f"{name}: must not be empty")
        return value

    def invalid(self, valid):
        out = [Invalid("type", [0.5]), Invalid("type", "0"), Invalid("range", [-1])]
        if not self.empty:
            out.append(Invalid("empty", []))
        return out



class Shape(Kind):
    """A batch shape: a sequence of non-negative integers (``torch.Size``, tuple, list; ``()`` for
    none). A bare integer is not a shape (``(runs,)``, not ``runs``). Converted to ``torch.Size``."""

    def __init__(self, *, optional: bool = False):
        self.optional = optional

    def describe(self):
        return "a shape (a sequence of non-negative integers)"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, torch.Size):
            return value
        if isinstance(value, (str, bytes, Tensor)) or not isinstance(value, Sequence):
            hint = f" (a batch of {value} runs is ({value},))" if isinstance(value, int) and \
                not isinstance(value, bool) else ""
            raise TypeError(f"{name}: expected a shape such as (runs,), got {value!r}{hint}")
        for size in value:
            if isinstance(size, bool) or not isinstance(size, numbers.Integral):
                raise TypeError(f"{name}: expected a sequence of integers, got the entry {size!r}")
            if size < 0:
                raise ValueError(f"{name}: sizes must be >= 0, got {int(size)}")
        return torch.Size(int(size) for size in value)

    def invalid(self, valid):
        return [Invalid("type", 3), Invalid("type", "3"), Invalid("type", (2.5,)), Invalid("range", (-1,))]



class FilePath(Kind):
    """A file path: a non-empty ``str`` or an ``os.PathLike`` (``pathlib.Path``)."""

    def __init__(self, *, optional: bool = False):
        self.optional = optional

    def describe(self):
        return "a file path"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if not isinstance(value, (str, os.PathLike)):
            raise TypeError(f"{name}: expected a file path (str or pathlib.Path), got {value!r}")
        if not os.fspath(value):
            raise ValueError(f"{name}: the path is empty")
        return value

    def invalid(self, valid):
        return [Invalid("type", 5), Invalid("value", "")]
