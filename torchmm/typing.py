"""Dimension vocabulary used in every ``Shapes:`` block of torchmm's docstrings.

=========  ==========================================================================
symbol     meaning
=========  ==========================================================================
``*B``     any number of leading batch dims (Monte Carlo runs, sensors, ...)
``T``      time steps; sequences are time-major ``(T, *B, ...)``
``M``      modes (models) of a multiple-model filter; the last batch axis of components
``Np``     particles of a particle belief, ``(*B, Np, n)``
``S``      sigma points, placed leftmost ``(S, *B, n)`` when models are called
``n``      state dimension (last axis of a mean, last two of a covariance)
``m``      measurement dimension
``k``      control-input dimension
``*P``     batch of a model's own parameters (e.g. ``(M,)`` for a mode bank); broadcasts
           against ``*B``
=========  ==========================================================================

Matrices are in math orientation: ``F: (n_out, n_in)`` applied as ``F @ x``. Vectors are 1-D in
their event dim (no ``(d, 1)`` columns). The transition matrix convention is
``P[i, j] = P(mode_k = j | mode_{k-1} = i)`` with rows summing to one. Missing measurements are
NaN. Nothing is inferred from shapes beyond broadcasting of leading batch dims.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from torch import Tensor

#: Alias used in annotations; the shapes are in each docstring's ``Shapes:`` block.
TensorLike = Tensor

__all__ = ["StepOutput", "TensorLike"]


class StepOutput(NamedTuple):
    """What every ``update``/``step`` returns.

    Attributes:
        belief: the posterior belief, batch ``(*B,)``.
        prior: the predicted belief the update started from, batch ``(*B,)``.
        log_likelihood: ``log p(z_k | z_{1:k-1})``, ``(*B,)``; exactly 0 where ``z_k`` is
            entirely missing (every component non-finite: NaN or ``+-inf``); NaN where the update
            failed (a present datum, a non-finite prediction: ``extras["failed"]``).
        innovation: ``z_k - E[z_k | z_{1:k-1}]``, ``(*B, m)`` (``(*B, M, m)`` per mode for
            multiple-model filters); non-finite where the measurement is missing.
        innovation_cov: its covariance ``S``, ``(*B, m, m)`` (per mode likewise).
        extras: filter-specific diagnostics (e.g. ``"mixed"`` beliefs of the IMM,
            ``"singular"`` flags of regularised innovation covariances, docs/robustness.md); a
            dict of tensors/beliefs with batch ``(*B, ...)``.
    """

    belief: Any
    prior: Any
    log_likelihood: Tensor
    innovation: Tensor | None = None
    innovation_cov: Tensor | None = None
    extras: dict | None = None

