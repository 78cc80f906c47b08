"""Answers kept while their objects are unchanged (issue 47: the one-shot call's fixed cost): a value check
that passed, a fingerprint, a factor, computed again only for other objects or after an in-place change."""

from __future__ import annotations

import weakref
from collections.abc import Sequence

from torch import Tensor

__all__ = ["Unchanged"]


class Unchanged:
    """What was computed from some objects, kept while they are unchanged: the same objects (held by weak
    reference, so no id is reused while an answer is kept) and, for tensors, at the same versions (torch's
    record of in-place changes, the one autograd trusts). What a value check passed, a fingerprint, a
    factor: the one-shot call's fixed cost (issue 47) without reading the same values again.

    As for autograd, a change that bypasses the version counter (through ``.data``, or a NumPy view of a
    tensor) is not seen: such a change after a first call keeps the first call's answer.

    Examples:
        >>> memo = Unchanged()
        >>> x = torch.ones(2)
        >>> memo.get((x,)) is None
        True
        >>> memo.put((x,), "checked")
        'checked'
        >>> memo.get((x,))
        'checked'
        >>> x.add_(1)  # an in-place change: a new version
        tensor([2., 2.])
        >>> memo.get((x,)) is None
        True
    """

    def __init__(self, size: int = 32):
        self.size = size
        self._answers: dict = {}

    @staticmethod
    def _key(objects: Sequence) -> tuple | None:
        try:
            return tuple((id(o), o._version if isinstance(o, Tensor) else None) for o in objects)
        except RuntimeError:  # a tensor made under torch.inference_mode has no version counter
            return None

    def get(self, objects: Sequence):
        """The answer kept for ``objects`` (a sequence of tensors and other weakly referable objects), or
        None where none is kept or one of them changed."""
        key = self._key(objects)
        hit = None if key is None else self._answers.get(key)
        if hit is None or any(ref() is not o for ref, o in zip(hit[0], objects)):
            return None
        return hit[1]

    def remember(self, objects: Sequence, compute):
        """The answer kept for ``objects``, else ``compute()``'s, kept unless None (an exception it raises
        keeps nothing): :meth:`get` and :meth:`put` with one look at the objects."""
        key = self._key(objects)
        hit = None if key is None else self._answers.get(key)
        if hit is not None and all(ref() is o for ref, o in zip(hit[0], objects)):
            return hit[1]
        answer = compute()
        return answer if answer is None or key is None else self._keep(key, objects, answer)

    def put(self, objects: Sequence, answer):
        """Keep ``answer`` (not None) for ``objects`` as they are now; returns it."""
        key = self._key(objects)
        return answer if key is None else self._keep(key, objects, answer)

    def _keep(self, key: tuple, objects: Sequence, answer):
        try:
            refs = tuple(weakref.ref(o) for o in objects)
        except TypeError:  # an object without weak references: nothing kept
            return answer
        if len(self._answers) >= self.size:  # (fresh objects every call: never more than size kept)
            self._answers.clear()
        self._answers[key] = (refs, answer)
        return answer
