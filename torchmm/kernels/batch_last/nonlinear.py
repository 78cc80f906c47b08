r"""The IMM and GPB1 over extended and unscented Kalman banks in the batch-last layout (issue 31).

:func:`~torchmm.run_filter` runs an :class:`~torchmm.IMM` or :class:`~torchmm.GPB1` over one
:class:`~torchmm.ExtendedKalmanFilter` or :class:`~torchmm.UnscentedKalmanFilter` (a mode bank: model
parameters with a trailing mode axis, as for the filter's own steps) through this kernel: the family
``"nonlinear_gaussian"`` (:class:`~torchmm.kernels.nonlinear.NonlinearGaussian`). It keeps the state as
:mod:`torchmm.kernels.batch_last.imm` does - one tensor ``(M, *B)`` per mean entry and per entry of the
covariances' upper triangle - and shares its mixing, mode posterior and estimate. The filters' own
models are called on batch-first *views* of that memory, one state component at a time
(:meth:`~torchmm.models.MotionModel.forward_entries`, :meth:`~torchmm.models.MotionModel.jacobian_entries`:
each component a contiguous slice, shaped ``(*B, M)`` as the steps give it), so every product of the
filter is a short sum of elementwise passes over all runs and modes, and a Jacobian entry a model
declares exactly 0 or 1 costs nothing. Every output is checked as the eager steps check theirs
(:func:`~torchmm.models.base.check_entries`, :func:`~torchmm.models.base.check_output`: shapes and dtypes
only). The step computes what the filters' steps compute, in the same
order:

- extended: ``F = df/dx (x)``, ``x- = f(x)``, ``P- = F P F^T + Q``; ``H = dh/dx (x-)``, ``C = P- H^T``,
  ``S = H C + R``, ``nu = z - h(x-)``;
- unscented: sigma points of ``(x, P)`` from the Cholesky factor (the rule's spread and weights),
  ``x-`` and ``P- = sum_s W^c_s d_s d_s^T + Q`` of the propagated points; new points of ``(x-, P-)``,
  ``z_pred``, ``S = sum_s W^c_s e_s e_s^T + R``, ``C = sum_s W^c_s (X_s - x-) e_s^T``. A covariance whose
  Cholesky factor fails takes :func:`~torchmm.linalg.psd_sqrt`'s (on the CPU, where the eager step reads
  the failure on the host too; elsewhere its pivot-clamped form, for every matrix);
- the conditioning as :func:`torchmm.linalg.condition` (missing components of ``z`` masked, the
  regularised factor of ``S`` with its singular flag, ``V = L^{-1} C^T``, ``w = L^{-1} nu``,
  ``x+ = x- + V^T w``, ``P+ = P- - V^T V``, the log-likelihood from the factor; ``m = 1`` in its
  closed form).

The unscented filter's Joseph form (float32's default) and sigma-point rules with their own ``points``
run the eager steps. Outputs equal the eager steps' to rounding (tests/multimodel/test_batch_last_nonlinear.py).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.linalg import pivot_clamped_cholesky, psd_sqrt, use_joseph
from torchmm.kernels.batch_last.algebra import (
    ONE,
    ZERO,
    Coef,
    cholesky_entries,
    coefficients,
    combine,
    factor,
    sandwich,
    solve_lower,
    stack_upper,
)
from torchmm.kernels.batch_last.imm import BatchLastIMM
from torchmm.kernels.batch_last.plan import PER_RUN_TRANSITION, described, planned
from torchmm.models.base import check_entries, check_output
from torchmm.runtime import host_reads_ok

__all__ = ["MIN_BATCH", "BatchLastNonlinear", "BatchLastNonlinearKernel", "NonlinearBank", "why_not_nonlinear"]

_LOG_2PI = math.log(2 * math.pi)

#: the fewest runs x modes for which the kernel is taken unasked (``fast_path=True`` and ``compile=True``
#: take it below):
#: its many small passes are bound by dispatch there, and the eager steps measured faster below about
#: 270 (n = 5, 3 modes; docs/performance.md)
MIN_BATCH = 300


def why_not_nonlinear(model, M: int, belief0, measurements) -> str | None:
    """Why a run of the description ``model`` (:class:`~torchmm.kernels.nonlinear.NonlinearGaussian` of an
    IMM or GPB1 over ``M`` modes) cannot run on this kernel, or None if it can: a belief that is not the
    ``ModeBelief`` of Gaussians ``(*B, M, n)``, measurements that are not one tensor ``(T, *B, m)`` of its
    dtype and device, a per-run transition ``(*B, M, M)``, the unscented Joseph form."""
    n, m = model.motion.state_dim, model.measurement.meas_dim
    if not isinstance(belief0, ModeBelief) or type(belief0.components) is not GaussianBelief:
        return "belief0 is not a ModeBelief of Gaussians"
    like = belief0.mode_log_probs
    if not isinstance(measurements, Tensor) or not measurements.is_floating_point():
        return "the measurements are not one floating-point tensor"
    batch = like.shape[:-1]
    if measurements.dim() != len(batch) + 2 or measurements.shape[1:] != (*batch, m):
        return "the measurements' batch differs from belief0's"
    if measurements.dtype != like.dtype or measurements.device != like.device:
        return "the measurements' dtype or device differs from belief0's"
    comps = belief0.components
    if comps.mean.shape != (*batch, M, n) or comps.cov.shape[-3:] != (M, n, n):
        return "belief0's components are not (*B, M, n)"
    if model.transition.dtype != like.dtype:
        return "the transition matrix's dtype differs from belief0's"
    if model.transition.dim() != 2:
        return PER_RUN_TRANSITION
    if model.kind == "unscented" and use_joseph(model.joseph, like.dtype):
        return "the unscented filter's Joseph form (float32's default; joseph=False takes the kernel)"
    return None


class NonlinearBank:
    """The model algebra of extended or unscented modes in the batch-last layout (module docstring): the models
    called on batch-first views, the predictions and updates of per-entry beliefs - the three calls of
    :class:`~torchmm.kernels.batch_last.bank.LinearBank` that the IMM step composes.

    Args:
        model: the filter's :class:`~torchmm.kernels.nonlinear.NonlinearGaussian` description (rule
            ``"mix"`` or ``"collapse"``) for which :func:`why_not_nonlinear` is None.
        M: the number of modes.
        batch_dims: ``len(B)``.
        like: a tensor of the run's dtype and device.
    """

    #: no traced graph: the models' Python runs every step (compiled with ``compile=True``)
    traceable = False

    def __init__(self, model, M: int, batch_dims: int, like: Tensor):
        self.motion, self.sensor = model.motion, model.measurement
        self.M, self.n, self.m, self.d = M, model.motion.state_dim, model.measurement.meas_dim, batch_dims
        self.unscented = model.kind == "unscented"
        d = batch_dims
        self.tiny = torch.finfo(like.dtype).tiny
        constant = lambda value: torch.full((), value, dtype=like.dtype, device=like.device)  # noqa: E731
        self.tiny_t, self.log_2pi, self.zero = constant(self.tiny), constant(_LOG_2PI), constant(0.0)
        self._to_front1 = (*range(1, d + 1), 0)  # (M, *B) -> (*B, M)
        self._to_back1 = (d, *range(d))  # (*B, M) -> (M, *B)
        self._to_front_s = (0, *range(2, d + 2), 1)  # (S, M, *B) -> (*B, M) behind the sigma points
        self._to_back_s = (0, d + 1, *range(1, d + 1))
        self._noise: dict = {}  # model -> (the tensor noise_cov returned at the entry point, its entries)
        if self.unscented:
            points = model.sigma_points
            wm, wc = points.weights(self.n, like.dtype, like.device)
            shape = (-1, *([1] * (d + 1)))
            self.wm, self.wc = wm.reshape(shape), wc.reshape(shape)
            self.spread, self.center = math.sqrt(points.spread(self.n)), points.include_center

    # -- the models, on batch-first views -----------------------------------------------------------
    def front(self, t: Tensor) -> Tensor:
        """``(M, *B)`` (or ``(S, M, *B)``) -> the batch-first view ``(*B, M)`` (``(S, *B, M)``)."""
        return t.permute(self._to_front1 if t.dim() == self.d + 1 else self._to_front_s)

    def back(self, t, points: bool = False):
        """A model's output, broadcasting to ``(*B, M)`` (``(S, *B, M)`` with ``points``), as ``(M, *B)``
        (``(S, M, *B)``); Python numbers as they are."""
        if not isinstance(t, Tensor):
            return t
        rank = self.d + 1 + points
        if t.dim() < rank:
            t = t.reshape(*([1] * (rank - t.dim())), *t.shape)
        return t.permute(self._to_back_s if points else self._to_back1)

    def coef(self, entry) -> Coef:
        """A model's entry (a tensor, or the numbers 0.0 and 1.0 declared exact) as a :class:`Coef`."""
        if isinstance(entry, Tensor):
            return Coef("tensor", self.back(entry))
        if entry == 0.0:
            return ZERO
        if entry == 1.0:
            return ONE
        return Coef("scalar", torch.full((), float(entry), dtype=self.tiny_t.dtype, device=self.tiny_t.device))

    def hold_noise(self, mean: Tensor) -> None:
        """Once per run, at the entry point: the noise covariances the models return at the start mean
        ``(*B, M, n)`` (batch-first), their entries classified (:func:`coefficients`: exact zeros skipped,
        one host read) where they are ``(n, n)`` or ``(M, n, n)``."""
        for model in (self.motion, self.sensor):
            cov = check_output(model, model.noise_cov(mean), mean, self._slot(model), "noise_cov")
            if cov.dim() <= 3 and cov.shape[:-2] in {(), (1,), (self.M,)}:
                self._noise[id(model)] = (cov, coefficients(cov, self.M, 2, self.d))

    def noise(self, model, xs: list) -> list:
        """``model.noise_cov(x)`` at the batch-first mean as per-entry :class:`Coef` ``[a][c]``: the
        classified entries (:meth:`hold_noise`) while the model returns the tensor it returned at the
        entry point (a fixed covariance), the entries as they come otherwise."""
        states = torch.stack([self.front(x) for x in xs], -1)
        cov = check_output(model, model.noise_cov(states), states, self._slot(model), "noise_cov")
        held = self._noise.get(id(model))
        if held is not None and held[0] is cov:
            return held[1]
        k = cov.shape[-1]
        return [[self.coef(cov[..., a, c]) for c in range(k)] for a in range(k)]

    def _slot(self, model) -> str:
        return "motion" if model is self.motion else "measurement"

    def forward_entries(self, model, front: list, points: bool = False) -> list:
        """``model.forward_entries`` at the batch-first views ``front`` (:meth:`front` of each component),
        checked (:func:`~torchmm.models.base.check_entries`), back in the kernel's layout."""
        call = model.forward_entries(front)
        return [self.back(t, points=points) for t in check_entries(model, call, front, self._slot(model))]

    def jacobian_entries(self, model, front: list) -> list:
        """``model.jacobian_entries`` at the batch-first views ``front``, checked, as :class:`Coef` rows."""
        rows = check_entries(model, model.jacobian_entries(front), front, self._slot(model), "jacobian")
        return [[self.coef(e) for e in row] for row in rows]

    def sigma_factor(self, Cs: list) -> list:
        """A square root ``L[a][c]`` (``L L^T = P``; None for an entry that is exactly 0) of the per-entry
        covariance (upper triangle ``Cs``) from which the sigma points are placed:
        :func:`~torchmm.linalg.psd_sqrt`'s - the Cholesky factor, and where it fails the eigen-factor (a
        full matrix; on the CPU, read on the host as the eager step reads it) or the pivot-clamped
        factor (elsewhere, for every matrix)."""
        n = self.n
        L, failed = cholesky_entries(Cs, None)
        if host_reads_ok(failed):
            if not bool(failed.any()):
                return L
            repair = psd_sqrt
        else:
            repair = pivot_clamped_cholesky
        P = stack_upper(Cs).permute(*range(2, self.d + 3), 0, 1)  # (M, *B, n, n)
        other = repair(P).permute(-2, -1, *range(self.d + 1))
        return [[torch.where(failed, other[a, c], self.zero if L[a][c] is None else L[a][c]) for c in range(n)]
                for a in range(n)]

    def sigma_points(self, xs: list, Cs: list) -> list:
        """Per component ``a``, the sigma points ``(S, M, *B)``: the centre (if the rule has one), then
        ``x + c L e_i``, then ``x - c L e_i`` (as :meth:`~torchmm.filters.SigmaPointStrategy.points`)."""
        n, spread = self.n, self.spread
        L = self.sigma_factor(Cs)
        out = []
        for a in range(n):
            x = xs[a]
            offsets = [None if L[a][i] is None else L[a][i] * spread for i in range(n)]
            plus = [x if o is None else x + o for o in offsets]
            minus = [x if o is None else x - o for o in offsets]
            out.append(torch.stack(([x] if self.center else []) + plus + minus))
        return out

    def moments(self, points: list) -> tuple[list, list]:
        """The weighted means ``(M, *B)`` and centred deviations ``(S, M, *B)`` of per-component points."""
        means = [(self.wm * p).sum(0) for p in points]
        return means, [p - mu for p, mu in zip(points, means)]

    def spread_sum(self, A: list, B: list, upper: bool) -> list:
        """``sum_s W^c_s A_s B_s^T`` entry by entry: ``[a][c]`` for every ``a``, ``c`` (``upper``: the
        upper triangle of ``A = B``)."""
        wA = [self.wc * t for t in A]
        if upper:
            return [[None] * a + [(wA[a] * B[c]).sum(0) for c in range(a, len(B))] for a in range(len(A))]
        return [[(wA[a] * B[c]).sum(0) for c in range(len(B))] for a in range(len(A))]

    # -- the step ---------------------------------------------------------------------------------
    def predict(self, xs: list, Cs: list, like: Tensor) -> tuple[list, list]:
        """Every mode's prediction from the per-entry start beliefs (extended or unscented)."""
        n, motion = self.n, self.motion
        Q = self.noise(motion, xs)
        if self.unscented:
            points = self.sigma_points(xs, Cs)
            moved = self.forward_entries(motion, [self.front(p) for p in points], points=True)
            xp, dev = self.moments(moved)
            S = self.spread_sum(dev, dev, upper=True)
            Pp = [[None] * a + [combine([(ONE, S[a][c])], Q[a][c]) for c in range(a, n)] for a in range(n)]
            return [x.expand_as(like) for x in xp], Pp
        front = [self.front(x) for x in xs]
        F = self.jacobian_entries(motion, front)
        xp = [t.expand_as(like) for t in self.forward_entries(motion, front)]
        return xp, sandwich(F, Cs, Q, like)

    def update(self, xp: list, Pp: list, zc: Tensor, ob: Tensor, nhob: Tensor, like: Tensor,
               flags: bool = True) -> tuple:
        """The measurement update of every mode (module docstring): the posterior ``xu``, ``Cu``, the
        log-likelihood ``(M, *B)``, the singular flags and, for the record, ``(h(x-), S)`` (``S`` entries
        ``[k][l]``, ``l <= k``)."""
        n, m, sensor = self.n, self.m, self.sensor
        R = self.noise(sensor, xp)
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        if self.unscented:
            points = self.sigma_points(xp, Pp)
            predicted = self.forward_entries(sensor, [self.front(p) for p in points], points=True)
            hx, zdev = self.moments(predicted)
            xdev = [p - x for p, x in zip(points, xp)]
            spread = self.spread_sum(zdev, zdev, upper=True)
            S = [[combine([(ONE, spread[c][k])], R[k][c]) for c in range(k + 1)] for k in range(m)]
            cross = self.spread_sum(zdev, xdev, upper=False)  # [k][a]
            C = [[cross[k][a] for k in range(m)] for a in range(n)]
        else:
            front = [self.front(x) for x in xp]
            H = self.jacobian_entries(sensor, front)
            hx = self.forward_entries(sensor, front)
            C = [[combine([(H[k][c], sym(Pp, a, c)) for c in range(n)], ZERO, like) for k in range(m)]
                 for a in range(n)]  # P- H^T
            S = [[combine([(H[k][a], C[a][c]) for a in range(n)], R[k][c], like) for c in range(k + 1)]
                 for k in range(m)]  # H P- H^T + R, lower triangle
        observed = ob > 0
        nu = [torch.where(observed[k], zc[k] - hx[k], 0.0) for k in range(m)]
        if m == 1:  # torchmm.linalg.condition's closed form
            s_raw = S[0][0]
            s = s_raw.clamp_min(self.tiny)
            gain = [C[a][0] * (ob[0] / s) for a in range(n)]
            xu = [torch.addcmul(xp[a], gain[a], nu[0]) for a in range(n)]
            Cu = [[None] * a + [torch.addcmul(Pp[a][c], gain[a], C[c][0], value=-1.0) for c in range(a, n)]
                  for a in range(n)]
            term = torch.addcdiv(s.log().add_(self.log_2pi), nu[0] * nu[0], s).mul_(-0.5)
            ll = torch.where(observed[0], term, 0.0)
            singular = (s_raw <= self.tiny) & observed[0] if flags else None
            return xu, Cu, ll, singular, (hx, S)
        one = self.tiny_t.new_ones(())
        masked = [[torch.where(observed[k] & observed[c], S[k][c], one if k == c else self.zero)
                   for c in range(k + 1)] for k in range(m)]
        L, singular = factor([[masked[c][k] if c >= k else None for c in range(m)] for k in range(m)],
                                  with_flag=True)
        rhs = [[C[a][k] * ob[k] for a in range(n)] + [nu[k]] for k in range(m)]
        solved = solve_lower(L, rhs)
        V, w = [row[:n] for row in solved], [row[n] for row in solved]
        xu = [xp[a] + combine([(Coef("tensor", V[k][a]), w[k]) for k in range(m)], ZERO, like) for a in range(n)]
        Cu = [[None] * a + [Pp[a][c] - combine([(Coef("tensor", V[k][a]), V[k][c]) for k in range(m)], ZERO, like)
                            for c in range(a, n)] for a in range(n)]
        quad = combine([(Coef("tensor", w[k]), w[k]) for k in range(m)], ZERO, like)
        count = ob.sum(0)
        half_log_det = combine([(ONE, L[k][k].log()) for k in range(m)], ZERO, like)
        ll = -0.5 * (quad + count * self.log_2pi) - half_log_det
        return xu, Cu, ll, singular if flags else None, (hx, S)

    def innovation(self, zraw, xp, Pp, s_first) -> tuple[Tensor, Tensor]:
        """The step's record of ``z - h(x-)`` ``(m, M, *B)`` (non-finite where missing) and ``S``
        ``(m, m, M, *B)``."""
        hx, S = s_first
        m, shape = self.m, xp[0].shape
        nu = torch.stack([(zraw[k] - hx[k]).expand(shape) for k in range(m)])
        return nu, torch.stack([torch.stack([S[max(k, c)][min(k, c)].expand(shape) for c in range(m)])
                                for k in range(m)])


class BatchLastNonlinear(BatchLastIMM):
    """The IMM (GPB1) step of :class:`~torchmm.kernels.batch_last.imm.BatchLastIMM` over extended or unscented
    modes (:class:`NonlinearBank`; module docstring).

    Args: as :class:`NonlinearBank`.
    """

    kind = "IMM over nonlinear modes"

    def __init__(self, model, M: int, batch_dims: int, like: Tensor):
        super().__init__(model, M, batch_dims, like, bank=NonlinearBank(model, M, batch_dims, like))


class BatchLastNonlinearKernel:
    """The registered kernel (:mod:`torchmm.kernels`) of the batch-last IMM, GPB1 and variable-structure
    IMM over extended and unscented modes: a filter that describes itself as nonlinear-Gaussian with the
    ``"mix"`` or ``"collapse"`` rule (and the VSIMM's model-set policy as its ``post_update``), a run
    without ``update_first``; any size and device, autograd, ``compile`` and ``record`` functions
    included."""

    name = "batch_last_nonlinear"
    by_size = True  # taken from MIN_BATCH runs x modes (kernels.by_size: studies switch it off)

    def plan(self, filter, belief0, measurements, request: kernels.Request):
        model = described(filter, request, "nonlinear_gaussian", ("mix", "collapse"), "IMM and GPB1", belief0,
                          measurements, why_not_nonlinear)
        if isinstance(model, str):
            return model
        M = model.transition.shape[-1]
        like = belief0.mode_log_probs
        if not (request.forced or request.compile_required) and like.numel() < MIN_BATCH:
            return (f"a small batch ({like.numel()} runs x modes < {MIN_BATCH}: the eager steps are faster; "
                    "fast_path=True or compile=True takes the kernel)")
        kernel = BatchLastNonlinear(model, M, like.dim() - 1, like)
        kernel.bank.hold_noise(belief0.components.mean)
        if request.compile:
            kernel.compile()
        kernel.prepare(measurements)
        return planned(kernel, belief0, request)


NONLINEAR = BatchLastNonlinearKernel()  # (registered by torchmm.kernels.TABLE)
