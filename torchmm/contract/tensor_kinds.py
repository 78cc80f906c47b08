"""The entry-point contract's kinds of tensors and beliefs (:mod:`torchmm.contract`): finite tensors,
covariances, transition matrices, value sets, probabilities, labels, masks, data, beliefs and parameter
lists - how an argument is checked against each and which invalid inputs the test suite tries. Split from
:mod:`torchmm.contract.kinds` (the base :class:`~torchmm.contract.kinds.Kind` and the scalar and option
kinds) by concern (issue 47)."""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from torchmm.contract.kinds import Equivalent, Invalid, Kind
from torchmm.validation import as_tensor, check_covariance, check_stochastic_rows

__all__ = [
    "BeliefArg",
    "Beliefs",
    "Cov",
    "Data",
    "Finite",
    "Labels",
    "Mask",
    "Probability",
    "Sets",
    "Stochastic",
    "Tensors",
    "Values",
]


def _perturb(valid, fn):
    try:
        return fn(torch.as_tensor(valid, dtype=torch.float64).clone())
    except Exception:  # noqa: BLE001 - no invalid input of this class can be built from the example
        return None



class Finite(Kind):
    """A tensor-like of finite reals (``square``: ``(..., d, d)``). ``check=False``: the function
    converts and checks it (the kind only declares what the tests try)."""

    def __init__(self, *, square: bool = False, optional: bool = False, check: bool = True,
                 vector: bool = False):
        self.square, self.optional, self.enforce, self.vector = square, optional, check, vector

    def describe(self):
        return "a tensor"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if isinstance(value, Tensor):
            if value.is_complex():
                raise TypeError(f"{name}: expected real numbers, got dtype {value.dtype}")
            if value.is_floating_point() and not bool(torch.isfinite(value.detach()).all()):
                raise ValueError(f"{name}: contains NaN or infinite entries")
            tensor = value
        else:
            tensor = as_tensor(value, name)
        if self.square and (tensor.dim() < 2 or tensor.shape[-1] != tensor.shape[-2]):
            raise ValueError(f"{name}: expected a square matrix (..., d, d), got shape {tuple(tensor.shape)}")
        return value

    def invalid(self, valid):
        out = [Invalid("type", "matrix")]
        bad = _perturb(valid, lambda t: (t.reshape(-1).index_fill_(0, torch.tensor([0]), math.nan)
                                         .reshape(t.shape)) if t.numel() else None)
        if bad is not None:
            out.append(Invalid("non-finite", bad))
        if self.square:
            bad = _perturb(valid, lambda t: t[..., :-1] if t.dim() >= 2 and t.shape[-1] > 1 else None)
            if bad is not None:
                out.append(Invalid("shape", bad))
        return out



class Cov(Finite):
    """A covariance ``(..., d, d)``: finite, symmetric, positive semi-definite (``definite``:
    positive definite), each relative to the matrix's scale."""

    def __init__(self, *, definite: bool = False, optional: bool = False, check: bool = True):
        super().__init__(square=True, optional=optional, check=check)
        self.definite = definite

    def describe(self):
        return "a covariance matrix"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if isinstance(value, Tensor) and value.is_complex():
            raise TypeError(f"{name}: expected real numbers, got dtype {value.dtype}")
        tensor = value if isinstance(value, Tensor) else as_tensor(value, name)
        check_covariance(tensor, name, definite=self.definite)
        return value

    def invalid(self, valid):
        out = super().invalid(valid)
        bad = _perturb(valid, lambda t: -t - torch.eye(t.shape[-1], dtype=t.dtype) if t.dim() >= 2 else None)
        if bad is not None:
            out.append(Invalid("non-PSD", bad))
        bad = _perturb(valid, lambda t: t + torch.triu(torch.ones_like(t), 1) * (1 + t.abs().max())
                       if t.dim() >= 2 and t.shape[-1] > 1 else None)
        if bad is not None:
            out.append(Invalid("non-symmetric", bad))
        return out



class Stochastic(Finite):
    """A row-stochastic matrix ``(..., M, M)`` (a mode transition)."""

    def __init__(self, *, optional: bool = False, check: bool = True):
        super().__init__(square=True, optional=optional, check=check)

    def describe(self):
        return "a row-stochastic matrix"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if not isinstance(value, (Tensor, list, tuple)):
            if callable(getattr(value, "matrix", None)):
                return value  # a ModeTransition checks itself
            raise TypeError(f"{name}: expected a row-stochastic matrix (M, M), got {type(value).__name__}")
        tensor = value if isinstance(value, Tensor) else as_tensor(value, name)
        check_stochastic_rows(tensor, name)
        return value

    def invalid(self, valid):
        if not isinstance(valid, (Tensor, list, tuple)):
            valid = getattr(valid, "matrix", lambda: None)()
        out = super().invalid(valid)
        bad = _perturb(valid, lambda t: 2 * t)
        if bad is not None:
            out.append(Invalid("non-stochastic", bad))
        return out



class Values(Kind):
    """A tensor-like of real numbers whose entries may be NaN or infinite (an estimate of a diverged
    run, log-probabilities, innovations with NaN = missing): only its type and dtype are checked
    (no value is read). Lists are converted to a tensor of the default dtype. ``floating``: a tensor
    of an integer or boolean dtype is refused (log-weights: ``-inf`` has no integer)."""

    def __init__(self, *, optional: bool = False, floating: bool = False):
        self.optional, self.floating = optional, floating

    def describe(self):
        return "a tensor of real numbers"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, Tensor):
            if value.is_complex():
                raise TypeError(f"{name}: expected real numbers, got dtype {value.dtype}")
            if self.floating and not value.is_floating_point():
                raise TypeError(f"{name}: expected floating-point values, got dtype {value.dtype}")
            return value
        if isinstance(value, (str, bytes)):
            raise TypeError(f"{name}: expected a tensor of real numbers, got the string {value!r}")
        try:
            out = torch.as_tensor(value, dtype=torch.get_default_dtype())
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"{name}: cannot convert to a tensor of real numbers ({err})") from None
        return out

    def invalid(self, valid):
        out = [Invalid("type", "values")]
        if isinstance(valid, Tensor) and valid.is_floating_point():
            out.append(Invalid("dtype", valid.to(torch.complex128)))
            if self.floating:
                out.append(Invalid("dtype", valid.nan_to_num().to(torch.int64)))
        return out



class Sets(Values):
    """A padded set ``(*B, D, m)`` of points or detections (``axis=-2``), or ``(*B, D)`` of numbers
    per element (``axis=-1``: log-weights per detection), whose size ``D`` may be 0. Checked as
    :class:`Values` (type and dtype; no value is read). An empty set is valid: where ``missing`` is
    given (NaN: an absent detection or a target that does not exist; ``-inf``: a zero weight) it must
    give exactly the result of the set of the same batch whose every element is ``missing``; with
    ``missing=None`` it must only be accepted. The tests try both (:meth:`equivalents`); ``mask``
    names the parameter that holds the set's presence flags ``(*B, D)``, emptied with it."""

    def __init__(self, *, axis: int = -2, missing: float | None = math.nan, mask: str | None = None,
                 optional: bool = False, floating: bool = False):
        super().__init__(optional=optional, floating=floating)
        self.axis, self.missing, self.mask = axis, missing, mask

    def describe(self):
        return "a padded set (a tensor)"

    def equivalents(self, valid):
        if not isinstance(valid, Tensor) or valid.dim() < -self.axis or not valid.is_floating_point():
            return []
        empty = valid.narrow(self.axis, 0, 0)
        reference = None if self.missing is None else torch.full_like(valid, self.missing)
        return [Equivalent("empty", empty, reference)]



class Probability(Kind):
    """A probability, or a tensor-like of probabilities (an existence per run or track), each in
    ``[0, 1]``. The check reads values (an entry point's check): not a string or a bool, real, no NaN,
    within ``[0, 1]``. Its size against the batch needs the belief: the function checks it (the tests
    try a tensor with an axis of 3 appended to the valid one, which cannot broadcast to its batch)."""

    def __init__(self, *, optional: bool = False):
        self.optional = optional

    def describe(self):
        return "a probability in [0, 1]"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if isinstance(value, (str, bytes, bool)) or type(value).__name__ == "bool_":
            raise TypeError(f"{name}: expected a probability in [0, 1] (a number or a tensor), got {value!r}")
        tensor = value
        if not isinstance(value, Tensor):
            try:
                tensor = torch.as_tensor(value, dtype=torch.get_default_dtype())
            except (TypeError, ValueError, RuntimeError) as err:
                raise TypeError(f"{name}: cannot convert to a tensor of probabilities ({err})") from None
        if tensor.is_complex() or tensor.dtype == torch.bool:
            raise TypeError(f"{name}: expected real probabilities, got dtype {tensor.dtype}")
        values = tensor.detach()
        if values.numel() and bool((values.isnan() | (values < 0) | (values > 1)).any()):
            bad = values[values.isnan() | (values < 0) | (values > 1)].reshape(-1)[0]
            raise ValueError(f"{name}: must be a probability in [0, 1], got {float(bad)}")
        return value

    def invalid(self, valid):
        out = [Invalid("type", "0.5"), Invalid("type", True), Invalid("non-finite", math.nan),
               Invalid("range", -0.1), Invalid("range", 1.5)]
        if isinstance(valid, (numbers.Real, Tensor)) and not isinstance(valid, bool):
            v = torch.as_tensor(valid, dtype=torch.float64)
            out.append(Invalid("shape", v.unsqueeze(-1).expand(*v.shape, 3).clone()))
            out.append(Invalid("non-finite", v.clone().reshape(-1).index_fill_(0, torch.tensor([0]), math.nan)
                               .reshape(v.shape)))
        return out



class Labels(Kind):
    """A tensor-like of integer indices (true modes, matched models), each at least ``minimum``;
    the upper bound (the number of modes) needs context and is checked by the function. Lists are
    converted to an int64 tensor."""

    def __init__(self, *, minimum: int = 0, optional: bool = False):
        self.minimum, self.optional = minimum, optional

    def describe(self):
        return "a tensor of integer indices"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if not isinstance(value, Tensor):
            if isinstance(value, (str, bytes)):
                raise TypeError(f"{name}: expected a tensor of integer indices, got the string {value!r}")
            try:
                value = torch.as_tensor(value)
            except (TypeError, ValueError, RuntimeError) as err:
                raise TypeError(f"{name}: cannot convert to a tensor of integer indices ({err})") from None
        if value.is_floating_point() or value.is_complex() or value.dtype == torch.bool:
            raise TypeError(f"{name}: expected integer indices, got dtype {value.dtype}")
        if value.numel() and bool((value < self.minimum).any()):
            raise ValueError(f"{name}: indices must be >= {self.minimum}, got {int(value.min())}")
        return value

    def invalid(self, valid):
        out = [Invalid("type", "0")]
        if isinstance(valid, Tensor) and valid.numel():
            out.append(Invalid("type", valid.to(torch.float64) + 0.5))
            out.append(Invalid("range", torch.full_like(valid, self.minimum - 1)))
        else:
            out.append(Invalid("range", [self.minimum - 1]))
        return out



class Mask(Kind):
    """A boolean tensor-like (availability, selection). Lists of bools are converted."""

    def __init__(self, *, optional: bool = False):
        self.optional = optional

    def describe(self):
        return "a boolean tensor"

    def check(self, value, name):
        if self._none(value, name):
            return value
        if not isinstance(value, Tensor):
            if isinstance(value, (str, bytes)):
                raise TypeError(f"{name}: expected a boolean tensor, got the string {value!r}")
            try:
                value = torch.as_tensor(value)
            except (TypeError, ValueError, RuntimeError) as err:
                raise TypeError(f"{name}: cannot convert to a boolean tensor ({err})") from None
        if value.dtype != torch.bool:
            raise TypeError(f"{name}: expected a boolean tensor, got dtype {value.dtype}")
        return value

    def invalid(self, valid):
        out = [Invalid("type", "yes")]
        if isinstance(valid, Tensor):
            out.append(Invalid("dtype", valid.to(torch.float64)))
        return out



class Data(Kind):
    """Measurements ``(T, *B, m)`` or ``(*B, m)`` (NaN = missing, so not invalid): the function
    checks them against its sensor and belief; the tests try a string, a wrong event size and an
    enlarged batch."""

    def __init__(self, *, optional: bool = False, time: bool = True):
        self.optional, self.time = optional, time

    def invalid(self, valid):
        out = [Invalid("type", "z")]
        if isinstance(valid, Tensor) and valid.dim() >= 1 and valid.is_floating_point():
            out.append(Invalid("shape", torch.cat([valid, valid[..., :1]], -1)))
            lead = 1 if self.time else 0
            if valid.dim() >= lead + 1:
                out.append(Invalid("shape", valid.unsqueeze(lead).expand(
                    *valid.shape[:lead], 2, *valid.shape[lead:]).contiguous()))
            out.append(Invalid("dtype", valid.to(torch.complex128)))
        return out



class BeliefArg(Kind):
    """A belief (:class:`~torchmm.beliefs.Belief`); ``validate``: its values are checked here
    (otherwise the function validates it). ``check=False``: the function checks its type too (it
    needs a particular belief type)."""

    def __init__(self, *, optional: bool = False, validate: bool = False, check: bool = True):
        self.optional, self.validate, self.enforce = optional, validate, check

    def describe(self):
        return "a belief"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if not _is_belief(value):
            raise TypeError(f"{name}: expected a belief (e.g. GaussianBelief), got {type(value).__name__}")
        if self.validate:  # (once for a belief unchanged since it passed: Belief.validate_once)
            getattr(value, "validate_once", value.validate)(name)
        return value

    def invalid(self, valid):
        out = [Invalid("type", torch.zeros(2)), Invalid("type", "belief")]
        if _is_belief(valid) and type(valid).__name__ == "GaussianBelief":
            make = type(valid)
            mean = valid.mean.detach().clone()
            mean.view(-1)[0] = math.nan
            out.append(Invalid("non-finite", make(mean, valid.cov)))
            cov = -valid.cov.detach() - torch.eye(valid.cov.shape[-1], dtype=valid.cov.dtype)
            out.append(Invalid("non-PSD", make(valid.mean, cov)))
            other = torch.float32 if valid.mean.dtype == torch.float64 else torch.float64
            out.append(Invalid("dtype", valid.to(other)))
        return out



def _is_belief(value) -> bool:
    """A :class:`~torchmm.beliefs.Belief` (by its interface: this layer sits below the beliefs)."""
    return callable(getattr(value, "validate", None)) and hasattr(type(value), "batch_shape")



class Beliefs(Kind):
    """A non-empty sequence of beliefs, or one belief whose last batch axis is the sequence (tracks
    to fuse). Declared only: the function checks each entry, naming it ``name[i]``; the tests try
    non-beliefs, an empty sequence, and (from Gaussian entries) a NaN mean, a non-PSD covariance
    and (in a sequence) an entry of another dtype than the others'."""

    def __init__(self, *, optional: bool = False):
        self.optional = optional

    def describe(self):
        return "a sequence of beliefs"

    def invalid(self, valid):
        out = [Invalid("type", torch.zeros(2)), Invalid("type", "beliefs"), Invalid("empty", [])]
        entries = [valid] if _is_belief(valid) else list(valid) if isinstance(valid, (list, tuple)) else []
        if entries:
            out.append(Invalid("type", [*entries[:-1], torch.zeros(2)]))
        last = entries[-1] if entries else None
        if _is_belief(last) and type(last).__name__ == "GaussianBelief":
            make = type(last)
            mean = last.mean.detach().clone()
            mean.view(-1)[0] = math.nan
            cov = -last.cov.detach() - torch.eye(last.cov.shape[-1], dtype=last.cov.dtype)
            other = torch.float32 if last.mean.dtype == torch.float64 else torch.float64
            trials = [("non-finite", make(mean, last.cov)), ("non-PSD", make(last.mean, cov))]
            if len(entries) > 1:  # an entry whose dtype differs from the others'
                trials.append(("dtype", last.to(other)))
            for cls, bad in trials:
                out.append(Invalid(cls, bad if _is_belief(valid) else [*entries[:-1], bad]))
        return out



class Tensors(Kind):
    """A non-empty tuple (or list) of tensors; ``leading``: sharing their leading axis (a scan's
    elements). ``check=False``: the function checks it (it takes any iterable of tensors, e.g. a
    module's ``parameters()``)."""

    def __init__(self, *, leading: bool = False, optional: bool = False, check: bool = True):
        self.leading, self.optional, self.enforce = leading, optional, check

    def describe(self):
        return "a tuple of tensors"

    def check(self, value, name):
        if not self.enforce or self._none(value, name):
            return value
        if isinstance(value, Tensor) or not isinstance(value, (tuple, list)) or not value:
            got = type(value).__name__
            raise TypeError(f"{name}: expected a non-empty tuple of tensors, got "
                            f"{'an empty ' + got if isinstance(value, (tuple, list)) else got}")
        bad = next((type(t).__name__ for t in value if not isinstance(t, Tensor)), None)
        if bad is not None:
            raise TypeError(f"{name}: expected a tuple of tensors, got a {bad}")
        if self.leading and any(t.dim() < 1 or t.shape[0] != value[0].shape[0] for t in value):
            raise ValueError(f"{name}: expected tensors sharing a leading axis, got shapes "
                             f"{[tuple(t.shape) for t in value]}")
        return value

    def invalid(self, valid):
        out = [Invalid("type", torch.zeros(2)), Invalid("type", "tensors"), Invalid("empty", ())]
        if isinstance(valid, (tuple, list)) and valid and isinstance(valid[0], Tensor):
            out.append(Invalid("type", (*valid[:-1], "x")))
            if self.leading and valid[0].dim() >= 1 and valid[0].shape[0] > 1:
                out.append(Invalid("shape", (*valid, valid[0][:-1])))
        return out
