r"""Markov mode-transition matrices.

Convention (stated once, used everywhere): ``P[i, j] = P(mode_k = j | mode_{k-1} = i)``; rows
sum to one; predicted mode probabilities are ``mu @ P``. This is Bar-Shalom's and FilterPy's
(code) orientation. Matrices printed the other way round must be transposed before use.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchmm.beliefs.ops import live_log
from torchmm.validation import as_tensor, check_stochastic_rows
from torchmm.contract import DType, Finite, Flag, Of, Real, Stochastic, Text, entry_point

__all__ = ["LogisticTransition", "ModeTransition", "StepTransition", "alpha_transition", "as_transition",
           "transition_alpha", "validate_transition"]


@entry_point(matrix=Stochastic(check=False), name=Text(label=True))
def validate_transition(matrix, name: str = "transition") -> Tensor:
    """Convert and check a row-stochastic transition matrix ``(..., M, M)``.

    Raises:
        ValueError: naming ``name`` if the matrix is not square, has negative entries, or has a
            row that does not sum to one.
    """
    matrix = as_tensor(matrix, name)
    check_stochastic_rows(matrix, name)
    return matrix


@entry_point(alpha=Finite(check=False), dtype=DType())
def alpha_transition(alpha, *, dtype=None) -> Tensor:
    r"""The ``m``-parameter transition matrix of paper 001, eq. (2.2).

    .. math::
        \pi_{ij} = \alpha_j \; (i \ne j), \qquad \pi_{jj} = 1 - \textstyle\sum_l \alpha_l + \alpha_j

    Rows sum to one by construction. (The matrix printed as (2.3) in the paper is the transpose of
    (2.2) and is column-stochastic; see ``docs/reproduction.md``.)

    Args:
        alpha: ``(..., M)`` non-negative, with ``sum(alpha) - alpha_j <= 1`` for every ``j``.

    Returns:
        ``(..., M, M)`` row-stochastic matrix.
    """
    alpha = as_tensor(alpha, "alpha", dtype=dtype)
    if alpha.dim() < 1 or alpha.shape[-1] < 1:
        raise ValueError(f"alpha: expected shape (..., M), got {tuple(alpha.shape)}")
    if bool((alpha.detach() < 0).any()):
        raise ValueError(f"alpha: entries must be non-negative, got {alpha.tolist()}")
    total = alpha.sum(-1, keepdim=True)
    diagonal = 1 - total + alpha
    if bool((diagonal.detach() < -1e-12).any()):
        raise ValueError(
            f"alpha: sum(alpha) - alpha_j must be <= 1 for every j (diagonal would be negative: "
            f"{diagonal.tolist()})"
        )
    M = alpha.shape[-1]
    eye = torch.eye(M, dtype=alpha.dtype, device=alpha.device)
    matrix = alpha.unsqueeze(-2).expand(*alpha.shape[:-1], M, M)
    return matrix * (1 - eye) + torch.diag_embed(diagonal.clamp_min(0))


@entry_point(matrix=Stochastic(), atol=Real(minimum=0.0))
def transition_alpha(matrix: Tensor, atol: float = 1e-12) -> Tensor | None:
    """The ``alpha`` of a matrix in the form (2.2), or ``None`` if it is not of that form.

    A matrix is of the form (2.2) when every column is constant off the diagonal
    (``pi_ij = alpha_j`` for all ``i != j``); then ``alpha_j`` is that value.

    Shapes:
        matrix: ``(M, M)`` -> ``(M,)`` or ``None``
    """
    M = matrix.shape[-1]
    if M == 1:
        return matrix.new_zeros(1)
    off = ~torch.eye(M, dtype=torch.bool, device=matrix.device)
    column_max = torch.where(off, matrix, -torch.inf).amax(-2)
    column_min = torch.where(off, matrix, torch.inf).amin(-2)
    if bool(((column_max - column_min).abs() > atol).any()):
        return None
    return column_max


class ModeTransition(nn.Module):
    """A transition matrix as a module: fixed (buffer) or learnable (row-wise softmax logits).

    Args:
        matrix: ``(M, M)`` row-stochastic matrix (validated).
        learnable: if true, the matrix is parametrised by logits ``log(matrix)`` as an
            ``nn.Parameter``; ``matrix()`` is then ``softmax(logits, -1)`` (rows stay stochastic).

    Examples:
        >>> t = ModeTransition(torch.tensor([[0.9, 0.1], [0.2, 0.8]]))
        >>> t.log_matrix().exp()
        tensor([[0.9000, 0.1000],
                [0.2000, 0.8000]])
    """

    @entry_point(matrix=Stochastic(check=False), learnable=Flag())
    def __init__(self, matrix, *, learnable: bool = False):
        super().__init__()
        matrix = validate_transition(matrix, "matrix")
        self.learnable = learnable
        if learnable:
            self.logits = nn.Parameter(matrix.detach().clamp_min(1e-12).log())
        else:
            self.register_buffer("value", matrix)

    @property
    def num_modes(self) -> int:
        return (self.logits if self.learnable else self.value).shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        """The matrix's batch: ``()`` for one ``(M, M)``, ``(*B,)`` for per-run matrices ``(*B, M, M)``."""
        return (self.logits if self.learnable else self.value).shape[:-2]

    def log_matrix(self) -> Tensor:
        """``log P`` (``-inf`` for zero entries). Shape ``(M, M)``. A zero entry passes no gradient (not
        ``log``'s ``1 / 0`` times a zero adjoint, NaN in every entry of its row's parametrisation: an estimated
        matrix's kept zeros, :class:`torchmm.learn.Param` ``"stochastic"``; tests/learn/test_transition_zeros.py)."""
        if self.learnable:
            return torch.log_softmax(self.logits, dim=-1)
        return live_log(self.value, 0.0) if self.value.requires_grad else self.value.log()

    def matrix(self) -> Tensor:
        """``P``, shape ``(M, M)``."""
        return self.log_matrix().exp() if self.learnable else self.value


class StepTransition:
    """One step's transition matrices ``(*B, M, M)`` (a :class:`LogisticTransition` at that step's inputs),
    with the interface the interactions read (``matrix()``, ``log_matrix()``, ``num_modes``)."""

    def __init__(self, log_matrix: Tensor):
        self._log = log_matrix

    @property
    def num_modes(self) -> int:
        return self._log.shape[-1]

    def log_matrix(self) -> Tensor:
        return self._log

    def matrix(self) -> Tensor:
        return self._log.exp()


class LogisticTransition(nn.Module):
    r"""Time-varying transition probabilities from inputs (statsmodels' ``exog_tvtp``): at step ``k`` the
    row of regime ``i`` is a multinomial logistic of the inputs ``x_k = u_k[columns]``,

    .. math::
        P(s_k = j \mid s_{k-1} = i, x_k) = \frac{\exp(x_k^\top \beta_{ij})}
        {1 + \sum_{l < M-1} \exp(x_k^\top \beta_{il})}, \quad j < M - 1,

    the last regime the reference (its logit 0). ``u_k`` is the step's controls (``run_filter(controls=)``;
    a regression's regressors may share them: ``columns`` picks the transition's).

    Args:
        coef: ``beta``, ``(M, M - 1, q)`` (a buffer: :func:`torchmm.learn.estimate` estimates it by name,
            ``"transition.coef"``).
        columns: the ``q`` columns of the controls that are the transition's inputs (a constant column of
            ones gives the intercept).

    ``matrix()`` and ``log_matrix()`` need the inputs: ``at(u)`` gives the step's :class:`StepTransition`.

    Examples:
        >>> t = LogisticTransition(torch.zeros(2, 1, 1), columns=[0])
        >>> t.at(torch.ones(3, 1)).matrix().shape   # three runs' matrices, all 0.5
        torch.Size([3, 2, 2])
    """

    takes_inputs = True

    @entry_point(coef=Finite(), columns=Of((list, tuple), what="a list of column indices"))
    def __init__(self, coef, columns):
        super().__init__()
        coef = as_tensor(coef, "coef")
        if coef.dim() != 3 or coef.shape[1] != coef.shape[0] - 1:
            raise ValueError(f"coef: expected (M, M - 1, q), got {tuple(coef.shape)}")
        columns = [int(c) for c in columns]
        if len(columns) != coef.shape[-1] or any(c < 0 for c in columns):
            raise ValueError(f"columns: expected {coef.shape[-1]} non-negative column indices (one per input), got "
                             f"{columns}")
        self.register_buffer("coef", coef)
        self.columns = columns

    @property
    def num_modes(self) -> int:
        return self.coef.shape[0]

    def at(self, u: Tensor | None) -> StepTransition:
        """The transition matrices at the step's controls ``u`` ``(*B, k)``: ``(*B, M, M)``."""
        if u is None:
            raise ValueError("controls: a LogisticTransition needs the step's inputs (run_filter(controls=...))")
        if u.shape[-1] <= max(self.columns):
            raise ValueError(f"controls: {u.shape[-1]} columns, but the transition reads column {max(self.columns)}")
        x = u[..., self.columns].to(self.coef.dtype)  # (*B, q)
        logits = torch.einsum("ijq,...q->...ij", self.coef, x)  # (*B, M, M - 1)
        logits = torch.cat([logits, torch.zeros_like(logits[..., :1])], dim=-1)
        return StepTransition(torch.log_softmax(logits, dim=-1))

    def matrix(self) -> Tensor:
        raise ValueError("transition: time-varying (LogisticTransition): its matrix is at(u).matrix() for a step's "
                         "inputs u")

    def log_matrix(self) -> Tensor:
        return self.matrix()


def as_transition(transition, name: str = "transition") -> ModeTransition:
    """``transition`` as a :class:`ModeTransition` (a matrix is validated; errors name ``name``); a
    :class:`LogisticTransition` is kept as it is."""
    if isinstance(transition, (ModeTransition, LogisticTransition)):
        return transition
    try:
        return ModeTransition(transition)
    except ValueError as err:
        raise ValueError(f"{name}: {str(err).removeprefix('matrix: ')}") from None
