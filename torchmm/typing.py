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

from torch import Tensor

#: Alias used in annotations; the shapes are in each docstring's ``Shapes:`` block.
TensorLike = Tensor

__all__ = ["TensorLike"]
