r"""The challenge match of paper 003, (32)-(34) and section 3.4.3 (split from :mod:`torchmm.multimodel.policies` by
concern, issue 47; re-exported there): the ``N`` heaviest of the ``M Np`` particles, found by the paper's
randomised tournament (vectorised over runs) or exactly by ``topk``; a model stays in the set if it has at
least ``Thre`` of the ``N`` winners (:class:`ChallengeMatch`)."""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

import torchmm.kernels.particle as particle_stages
from torchmm.beliefs import ModeBelief, ParticleBelief
from torchmm.beliefs.ops import normalize_log_probs
from torchmm.contract import Choice, Int, entry_point
from torchmm.multimodel.structure import mode_filters, particle_counts
from torchmm.validation import as_int

__all__ = ["ChallengeMatch", "challenge_match"]


# ------------------------------------------------------------------------------------------------
# challenge match
# ------------------------------------------------------------------------------------------------
def challenge_match(scores: Tensor, num_winners: int, *, passes: int = 1,
                    generator: torch.Generator | None = None) -> Tensor:
    """The randomised tournament of paper 003, section 3.4.3, for the ``N`` heaviest particles.

    a) a random ``N`` particles form sequence 1; b) ``N`` further particles, taken from the
    remaining pool in a random order (a random affine permutation per run), form sequence 2; c) the two sequences are compared position
    by position (sequence 1 rotated by a random offset each round) and a heavier challenger takes
    the place of the holder, who goes back to the pool; d) b)-c) repeat until every pool position
    has challenged ``passes`` times (the last window padded with a particle that never wins).
    Since a holder is only replaced by a strictly heavier challenger, the holder of position
    ``p`` after a pass is the first maximum over it and its challengers, so a whole pass is a
    handful of tensor ops over all runs and rounds at once (``max``; ``cummax`` to send the
    losers back to the pool when another pass follows), equal to the round-by-round loop.
    The number of true top-``N`` particles held never decreases, and with enough passes the
    result equals ``topk`` (for distinct scores).

    Returns:
        indices of the winners into the last axis of ``scores``, ``(*B, N)`` (unordered).

    Shapes:
        scores: ``(*B, P)`` (e.g. log-weights of all ``M Np`` particles) -> ``(*B, N)``
    """
    P = scores.shape[-1]
    if not 1 <= num_winners <= P:
        raise ValueError(f"num_winners: must be in [1, {P}], got {num_winners}")
    if passes < 0:
        raise ValueError(f"passes: must be >= 0, got {passes}")
    batch = scores.shape[:-1]
    flat = scores.reshape(batch.numel(), P)
    Bf, device = flat.shape[0], flat.device
    pool_size = P - num_winners
    if passes == 1 and pool_size > 0 and particle_stages.applies(flat):
        # the same pass from the same random numbers in one compiled loop (torchmm.kernels.particle)
        a, b = _affine_coefficients(Bf, P, device, generator)
        rounds = math.ceil(pool_size / num_winners)
        shifts = torch.randint(0, num_winners, (rounds * Bf, 1), device=device, generator=generator)
        winners = particle_stages.challenge_pass(flat, a.view(Bf), b.view(Bf), shifts.view(rounds, Bf), num_winners)
        return winners.view(*batch, num_winners)
    order = _random_affine_permutation(Bf, P, device, generator)
    seq1 = order[:, :num_winners].contiguous()
    pool = order[:, num_winners:].contiguous()
    held = torch.gather(flat, 1, seq1)
    if pool_size > 0 and passes > 0:
        N = num_winners
        rounds = math.ceil(pool_size / N)
        # every round's rotation at once (the same random stream as one draw per round)
        shifts = torch.randint(0, N, (passes * rounds * Bf, 1), device=device, generator=generator)
        shifts = shifts.view(passes, rounds, Bf, 1).transpose(1, 2)  # (passes, Bf, rounds, 1)
        ar = torch.arange(N, device=device)
        meet = ar - shifts  # holder p meets challenger (p - shift) mod N of the round's window
        meet += N * (meet < 0)
        # the pool as `rounds` windows of N, the last one padded with a dummy particle (index P,
        # score -inf) that never wins; the dummy scores sit in an extra column of the score table
        pad = rounds * N - pool_size
        table = flat
        if pad:
            table = torch.cat([flat, torch.full((Bf, 1), -math.inf, dtype=flat.dtype, device=device)], 1)
            dummy = torch.full((Bf, pad), P, dtype=pool.dtype, device=device)
        for p in range(passes):  # over tournament passes (default 1), not over runs or particles
            windows = (torch.cat([pool, dummy], 1) if pad else pool).view(Bf, rounds, N)
            challengers = torch.gather(windows, 2, meet[p])  # (Bf, rounds, N), in meeting order
            challenger_scores = torch.gather(table, 1, challengers.view(Bf, rounds * N)).view(Bf, rounds, N)
            # holder p after all rounds is the running maximum over its challengers, ties to the
            # earlier one (a challenger replaces the holder only if strictly heavier)
            if p == passes - 1:
                top, arg = challenger_scores.max(1)  # first maximum among the challengers
                win = top > held
                held = torch.where(win, top, held)
                seq1 = torch.where(win, torch.gather(challengers, 1, arg.unsqueeze(1)).squeeze(1), seq1)
                break
            cand = torch.cat([held.unsqueeze(1), challenger_scores], 1)  # (Bf, rounds + 1, N)
            cand_index = torch.cat([seq1.unsqueeze(1), challengers], 1)
            # losers go back to the pool slot of the challenger they met (for the next pass):
            # the holder of round r is the candidate of the last strict improvement up to r
            best, _ = torch.cummax(cand, 1)
            win = challenger_scores > best[:, :-1]
            steps = torch.arange(rounds + 1, device=device).view(1, -1, 1)
            changed = torch.cat([torch.ones_like(win[:, :1]), win], 1)
            last, _ = torch.cummax(torch.where(changed, steps, torch.zeros_like(steps)), 1)
            holder = torch.gather(cand_index, 1, last)  # (Bf, rounds + 1, N)
            losers = torch.where(win, holder[:, :-1], challengers)  # in meeting order
            back = (ar + shifts[p]) % N  # challenger slot k met holder (k + shift) mod N
            pool = torch.gather(losers, 2, back).reshape(Bf, -1)[:, :pool_size].contiguous()
            held, seq1 = best[:, -1], holder[:, -1]
    return seq1.view(*batch, num_winners)


@functools.lru_cache(maxsize=16)
def _units(size: int) -> Tensor:
    return torch.tensor([a for a in range(1, size) if math.gcd(a, size) == 1] or [1])


def _random_affine_permutation(rows: int, size: int, device, generator) -> Tensor:
    """Per row a random permutation ``j -> (a j + b) mod size`` (``a`` coprime with ``size``).

    O(size) instead of a sort; the tournament's random meeting order (random rotations each
    round) does the rest.

    Shapes:
        -> ``(rows, size)`` int64
    """
    a, b = _affine_coefficients(rows, size, device, generator)
    j = torch.arange(size, device=device)
    return (a * j + b) % size


def _affine_coefficients(rows: int, size: int, device, generator) -> tuple[Tensor, Tensor]:
    """The random ``(a, b)`` of :func:`_random_affine_permutation`, each ``(rows, 1)`` int64."""
    units = _units(size).to(device)
    pick = torch.randint(0, units.numel(), (rows, 1), device=device, generator=generator)
    a = units[pick]
    b = torch.randint(0, size, (rows, 1), device=device, generator=generator)
    return a, b


class ChallengeMatch:
    """Keep the models with at least ``threshold`` of the ``num_winners`` heaviest particles.

    Args:
        num_winners: ``N`` (paper: 420).
        threshold: ``Thre`` (paper: 23).
        method: ``"cm"`` (the randomised tournament, :func:`challenge_match`) or ``"topk"`` (exact).
        passes: tournament passes over the pool (the paper leaves the end condition open).

    If no model reaches the threshold, the model with the most winners is kept (the set is never
    empty); ``info["fallback"]`` marks those runs. A ``threshold`` above ``num_winners`` could never be
    reached (every step would fall back) and is refused.
    """

    @entry_point(num_winners=Int(1), threshold=Int(0), method=Choice("cm", "topk"), passes=Int(1))
    def __init__(self, num_winners: int = 420, threshold: int = 23, *, method: str = "cm", passes: int = 1):
        self.num_winners = as_int(num_winners, "num_winners", minimum=1)
        self.threshold = as_int(threshold, "threshold", minimum=0)
        if self.threshold > self.num_winners:
            raise ValueError(f"threshold: {self.threshold} exceeds num_winners ({self.num_winners}): no "
                             "model could reach it (every step would fall back to the model with the most "
                             "winners)")
        self.method, self.passes = method, as_int(passes, "passes", minimum=0)

    def check_bank(self, bank, name: str = "policy") -> None:
        """Refuse a bank of mode filters that are not particle filters (``TypeError``) and more winners than
        the bank's ``M x Np`` particles (``ValueError`` naming ``name.num_winners``); called once by
        :class:`~torchmm.multimodel.VariableStructureIMM` when it is built (a bank whose filters are
        not known is left to the step's checks)."""
        filters = mode_filters(bank)
        if filters is None:
            return
        counts = particle_counts(bank)
        if counts is None:
            kinds = sorted({type(f).__name__ for f in filters})
            raise TypeError(f"{name}: ChallengeMatch ranks particles and needs particle mode filters "
                            f"(ParticleFilter), got {', '.join(kinds)}; use ExactMinimumEntropy over other "
                            "banks")
        if all(c is not None for c in counts) and self.num_winners > sum(counts):
            shown = f"{len(counts)} x {counts[0]} = " if len(set(counts)) == 1 else ""
            raise ValueError(f"{name}.num_winners: {self.num_winners} exceeds the bank's "
                             f"{shown}{sum(counts)} particles")

    def __call__(self, log_weights: Tensor, generator=None) -> tuple[Tensor, dict]:
        M, Np = log_weights.shape[-2:]
        if self.num_winners > M * Np:
            raise ValueError(f"num_winners: {self.num_winners} exceeds the {M} x {Np} = {M * Np} particles")
        scores = log_weights.flatten(-2)
        if self.method == "topk":
            winners = torch.topk(scores, self.num_winners, dim=-1).indices
        else:
            winners = challenge_match(scores, self.num_winners, passes=self.passes, generator=generator)
        model = torch.div(winners, Np, rounding_mode="floor")
        counts = torch.zeros(*scores.shape[:-1], M, dtype=log_weights.dtype, device=log_weights.device)
        counts.scatter_add_(-1, model, torch.ones_like(model, dtype=counts.dtype))
        active = counts >= self.threshold
        empty = ~active.any(-1)
        # (one_hot checks its indices on the host; a comparison with arange does not)
        best = counts.argmax(-1, keepdim=True) == torch.arange(M, device=counts.device)
        active = torch.where(empty.unsqueeze(-1), best, active)
        return active, {"winner_counts": counts, "fallback": empty}

    def select(self, belief: ModeBelief, generator=None) -> tuple[Tensor, dict]:
        """The policy over a bank of particle filters: the joint weights of every model's particles."""
        comps = belief.components
        if not isinstance(comps, ParticleBelief):
            raise TypeError(f"ChallengeMatch: needs particle mode filters (it ranks particles), got beliefs of type "
                            f"{type(comps).__name__}; use ExactMinimumEntropy for other banks")
        joint = belief.mode_log_probs.unsqueeze(-1) + normalize_log_probs(comps.log_weights)
        return self(joint, generator)
