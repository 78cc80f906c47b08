r"""The entry-point contract: one mechanism that every public function and constructor goes through.

Every public entry point of torchmm declares the *kind* of each of its parameters with
:func:`entry_point`::

    @entry_point(bank=Bank(), transition=Stochastic(), generator=Gen(optional=True), feedback=Flag())
    def __init__(self, bank, transition, *, generator=None, feedback=True): ...

The declaration does two things, both by construction:

* **at run time**, the wrapper checks every argument the caller passed against its kind once, at
  entry (a size is an integer, a flag a bool, a generator a :class:`torch.Generator`, a covariance
  finite, symmetric and PSD relative to its scale, a transition row-stochastic, a policy an
  instance and not a class, ...) and raises a ``TypeError`` or ``ValueError`` whose message starts
  with the parameter's name. Defaults are trusted; nothing runs inside a filter step.
* **in the test suite**, each kind lists the classes of invalid input that apply to it
  (:meth:`Kind.invalid`: wrong types, non-finite values, non-PSD matrices, non-stochastic rows,
  zero and empty sizes, wrong shapes and dtypes, classes for instances, ...).
  ``tests/robustness/test_api_contract.py`` enumerates the public API (``torchmm.__all__`` and every
  subpackage's), requires every public callable to be registered here (or listed, with a reason,
  as not an entry point), and calls each entry point with each invalid input of each declared
  parameter in place of a valid example's argument: every call must raise ``TypeError`` or
  ``ValueError`` naming the parameter. A new public function, or a new parameter, without a
  declaration is a red test (the decorator refuses a signature with an undeclared parameter at
  import).

The kinds live in :mod:`torchmm.contract.kinds` (and :mod:`torchmm.contract.tensor_kinds`), the decorator in
:mod:`torchmm.contract.engine`.

Some kinds only *declare* (:class:`Data`, :class:`BeliefArg`, :class:`Of` with ``check=False``):
the function checks the argument itself because the check needs context (the sensor's dimension,
the filter's dtype), and the kind's invalid inputs test that it does. ``docs/robustness.md``
describes the contract.
"""

from torchmm.contract import engine, kinds, tensor_kinds
from torchmm.contract.engine import *  # noqa: F403  (the decorator and the registry)
from torchmm.contract.kinds import *  # noqa: F403  (the parameter kinds)
from torchmm.contract.tensor_kinds import *  # noqa: F403  (the kinds of tensors and beliefs)

__all__ = [*engine.__all__, *kinds.__all__, *tensor_kinds.__all__]
