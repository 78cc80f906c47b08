"""The linear-Gaussian whole-run kernel (torchmm/kernels/linear.py) against the eager steps and theory.

Every comparison runs the kernel (``fast_path=True``) and the eager steps (``fast_path=False``, an
independent implementation in the same library) on the same data, or checks the kernel against exact
Gaussian algebra (the marginal likelihood of a linear-Gaussian model) and finite differences.
"""

from __future__ import annotations

import pytest
import torch
import torch.utils._pytree as pytree
from torch.testing import assert_close

from torchmm import (
    GPB1,
    GPB2,
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    ModeTransition,
    StaticMM,
    run_filter,
)
from torchmm.kernels import linear, linear_run
from torchmm.learn import negative_log_likelihood
from torchmm.models import LinearMeasurement, LinearMotion, learnable_noise
from torchmm.run import Keep

KINDS = ["kf", "imm", "gpb1", "static"]
TIGHT = {"rtol": 1e-10, "atol": 1e-10}


@pytest.fixture(scope="module", autouse=True)
def _numba_loaded():
    """The compiled loops loaded (and Numba imported), as after a first likelihood evaluation."""
    linear.load()


@pytest.fixture(autouse=True)
def _short_runs_take_the_kernel(monkeypatch):
    """The tests' runs are short (10-20 steps): by default (``LONG_RUN``) they would step eagerly;
    here the default takes the kernel wherever it applies (test_long_run_rule tests the rule)."""
    monkeypatch.setattr(linear, "LONG_RUN", 0)


@pytest.fixture
def calls(monkeypatch):
    """Counts of the kernel's runs: ``tried`` (the compiled loop ran) and ``used`` (its fields were
    returned; a run that failed at run time is re-run eagerly and not counted here)."""
    counts = {"tried": 0, "used": 0}
    forward, fields = linear_run.Run.forward, linear._fields

    def counting_forward(*args):  # (through autograd's apply, or called directly without a graph)
        counts["tried"] += 1
        return forward(*args)

    def counting_fields(*args, **kwargs):
        counts["used"] += 1
        return fields(*args, **kwargs)

    monkeypatch.setattr(linear_run.Run, "forward", staticmethod(counting_forward))
    monkeypatch.setattr(linear, "_fields", counting_fields)
    return counts


# ------------------------------------------------------------------------------------------------ data


def params(kind: str, n: int = 3, m: int = 2, M: int = 3, B=(4,), T: int = 10, seed: int = 0,
           missing: bool = True, dtype=torch.float64, grad: bool = False) -> tuple[dict, torch.Tensor]:
    """Random model matrices, start belief and measurements ``(T, *B, m)`` (NaN: missing data)."""
    g = torch.Generator().manual_seed(seed)

    def r(*shape):
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    def spd(d, *batch):
        A = r(*batch, d, d)
        return A @ A.mT / d + 0.5 * torch.eye(d, dtype=torch.float64)

    P = () if kind == "kf" else (M,)
    p = {
        "F": torch.eye(n, dtype=torch.float64) + 0.3 * r(*P, n, n),
        "b": 0.2 * r(*P, n),
        "Q": 0.2 * spd(n, *P),
        "H": r(m, n),
        "R": spd(m, *P),
        "x0": r(*B, n),
        "P0": spd(n, *B),
    }
    if kind != "kf":
        p["mp"] = torch.softmax(r(M), -1)
        if kind != "static":
            p["Pi"] = torch.softmax(r(M, M) + 2.0 * torch.eye(M, dtype=torch.float64), -1)
    z = 2.0 * r(T, *B, m)
    if missing:
        if not B:
            z[3, 0] = float("nan")
        else:
            z[3, 1 % B[0], 0] = float("nan")  # one component of one run
            z[7, 2 % B[0], m - 1] = float("nan")
        z[5] = float("nan")  # a whole step
    p = {k: v.to(dtype).requires_grad_(grad) for k, v in p.items()}
    return p, z.to(dtype)


def make(kind: str, p: dict, *, joseph: bool = False):
    """The filter and its start belief built from ``p`` (so that gradients reach ``p``'s tensors)."""
    kf = KalmanFilter(LinearMotion(p["F"], p["Q"], offset=p["b"]), LinearMeasurement(p["H"], p["R"]),
                      joseph=joseph)
    belief0 = GaussianBelief(p["x0"], p["P0"])
    if kind == "kf":
        return kf, belief0
    M = p["mp"].shape[-1]
    f = {"imm": lambda: IMM(kf, p["Pi"]), "gpb1": lambda: GPB1(kf, p["Pi"]),
         "static": lambda: StaticMM(kf, M)}[kind]()
    return f, f.initial_belief(belief0, p["mp"])


def fields(traj) -> list:
    return [traj.belief, traj.prior, traj.log_likelihood, traj.innovation, traj.innovation_cov, traj.extras]


def assert_same(a, e, **tol) -> None:
    """Two trajectories: the same pytree structure (None fields included), equal values, NaN where
    the other has NaN."""
    tol = tol or TIGHT
    fa, sa = pytree.tree_flatten(fields(a))
    fe, se = pytree.tree_flatten(fields(e))
    assert sa == se
    for x, y in zip(fa, fe):
        if isinstance(y, torch.Tensor):
            assert x.shape == y.shape and x.dtype == y.dtype
            assert_close(x, y, equal_nan=True, **tol)
        else:
            assert x == y


def gaussian(belief):
    """The Gaussian part of a belief (a mode belief's components)."""
    return belief if isinstance(belief, GaussianBelief) else belief.components


def sym(t: torch.Tensor) -> torch.Tensor:
    return (t + t.mT) / 2


# ------------------------------------------------------------------------------- 1. forward equality

SHAPES = [(3, 2, 3), (2, 1, 2), (1, 1, 2), (1, 2, 3), (2, 3, 2)]  # (n, m, M): m = 1, n = 1, m = 3


@pytest.mark.parametrize("update_first", [False, True])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: f"n{s[0]}m{s[1]}M{s[2]}")
def test_forward_equals_eager(kind, update_first, shape, calls):
    n, m, M = shape
    p, z = params(kind, n, m, M, seed=10 * SHAPES.index(shape) + KINDS.index(kind))
    f, b0 = make(kind, p)
    with torch.no_grad():
        fast = run_filter(f, b0, z, update_first=update_first, fast_path=True)
        assert calls == {"tried": 1, "used": 1}
        eager = run_filter(f, b0, z, update_first=update_first, fast_path=False)
    assert calls["tried"] == 1
    assert_same(fast, eager)
    # the data really were partly missing: NaN innovations, and the whole missing step adds nothing
    assert torch.isnan(eager.innovation).any()
    assert torch.equal(fast.log_likelihood[5], torch.zeros_like(fast.log_likelihood[5]))
    assert torch.isfinite(fast.log_likelihood).all()
    # ... and leaves the belief as predicted (no update)
    assert_close(gaussian(fast.belief).mean[5], gaussian(fast.prior).mean[5], **TIGHT)
    assert_close(gaussian(fast.belief).cov[5], gaussian(fast.prior).cov[5], **TIGHT)
    if kind == "imm" and not update_first:
        assert "mixed" in fast.extras


@pytest.mark.parametrize("kind", KINDS)
def test_forward_estimate_record_equals_eager(kind, calls):
    p, z = params(kind, seed=11)
    f, b0 = make(kind, p)
    fast = run_filter(f, b0, z, record="estimate", fast_path=True)
    assert calls["used"] == 1
    eager = run_filter(f, b0, z, record="estimate", fast_path=False)
    assert fast.prior is None and fast.innovation is None and fast.extras is None
    assert_same(fast, eager)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)], ids=str)
def test_forward_batch_shapes(batch, calls):
    p, z = params("imm", B=batch, seed=5)
    f, b0 = make("imm", p)
    with torch.no_grad():
        fast = run_filter(f, b0, z, fast_path=True)
        eager = run_filter(f, b0, z, fast_path=False)
    assert calls["used"] == 1
    assert fast.log_likelihood.shape == (10, *batch)
    assert_same(fast, eager)


# ------------------------------------------------------------------------------------- theory checks


def exact_log_likelihood(p: dict, z: torch.Tensor, update_first: bool, mode: int | None = None) -> torch.Tensor:
    """``log p(z_{1:T})`` per run of the linear-Gaussian model, from the joint Gaussian of all
    observed measurement components (no filter)."""
    pick = (lambda t: t) if mode is None else (lambda t: t[mode])
    F, b, Q, R = pick(p["F"]), pick(p["b"]), pick(p["Q"]), pick(p["R"])
    H = p["H"]
    T, B, m = z.shape
    n = F.shape[-1]
    steps = [k + (0 if update_first else 1) for k in range(T)]  # the state index of each measurement
    powers = [torch.eye(n, dtype=F.dtype)]
    for _ in range(max(steps)):
        powers.append(F @ powers[-1])
    out = []
    for run in range(B):
        x0, P0 = p["x0"][run], p["P0"][run]
        means = [powers[s] @ x0 + sum((powers[s - j] @ b for j in range(1, s + 1)), torch.zeros(n)) for s in steps]
        mean = torch.cat([H @ mu for mu in means])
        cov = torch.zeros(T * m, T * m, dtype=F.dtype)
        for i, s in enumerate(steps):
            for k, t in enumerate(steps):
                c = powers[s] @ P0 @ powers[t].T
                for j in range(1, min(s, t) + 1):
                    c = c + powers[s - j] @ Q @ powers[t - j].T
                block = H @ c @ H.T + (R if i == k else 0)
                cov[i * m:(i + 1) * m, k * m:(k + 1) * m] = block
        zz = z[:, run].reshape(-1)
        seen = torch.isfinite(zz)
        dist = torch.distributions.MultivariateNormal(mean[seen], cov[seen][:, seen])
        out.append(dist.log_prob(zz[seen]))
    return torch.stack(out)


@pytest.mark.parametrize("update_first", [False, True])
@pytest.mark.parametrize("shape", [(2, 2), (1, 1), (3, 3)], ids=str)
def test_kf_likelihood_is_the_exact_marginal(shape, update_first, calls):
    n, m = shape
    p, z = params("kf", n, m, B=(4,), T=9, seed=21)
    f, b0 = make("kf", p)
    traj = run_filter(f, b0, z, update_first=update_first, fast_path=True, record=Keep("log_likelihood"))
    assert calls["used"] == 1
    assert_close(traj.log_likelihood.sum(0), exact_log_likelihood(p, z, update_first), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("update_first", [False, True])
def test_static_bank_is_the_exact_mixture(update_first, calls):
    """A static bank: ``log p(z) = logsumexp_j(log mu_j + log p_j(z))`` and the final mode posterior is
    Bayes' rule over the modes' exact marginal likelihoods."""
    p, z = params("static", 2, 2, 3, B=(4,), T=9, seed=22)
    f, b0 = make("static", p)
    traj = run_filter(f, b0, z, update_first=update_first, fast_path=True)
    assert calls["used"] == 1
    per_mode = torch.stack([exact_log_likelihood(p, z, update_first, j) for j in range(3)], -1)  # (B, M)
    joint = p["mp"].log() + per_mode
    total = torch.logsumexp(joint, -1)
    assert_close(traj.log_likelihood.sum(0), total, rtol=1e-10, atol=1e-10)
    assert_close(traj.belief.mode_log_probs[-1], joint - total[:, None], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("kind", ["imm", "gpb1", "static"])
def test_identical_modes_are_one_kalman_filter(kind, calls):
    """Modes with the same models: every interaction reduces to the Kalman filter of that model."""
    pk, z = params("kf", 3, 2, B=(4,), seed=23)
    p = {k: v.expand(2, *v.shape).clone() if k in ("F", "b", "Q", "R") else v for k, v in pk.items()}
    p["mp"] = torch.tensor([0.3, 0.7])
    p["Pi"] = torch.tensor([[0.9, 0.1], [0.4, 0.6]])
    f, b0 = make(kind, p)
    kf, kb0 = make("kf", pk)
    with torch.no_grad():
        mm = run_filter(f, b0, z, fast_path=True)
        single = run_filter(kf, kb0, z, fast_path=True)
    assert calls["used"] == 2
    assert_close(mm.log_likelihood, single.log_likelihood, rtol=1e-10, atol=1e-10)
    est = mm.belief.estimate()
    assert_close(est.mean, single.belief.mean, rtol=1e-10, atol=1e-10)
    assert_close(est.cov, single.belief.cov, rtol=1e-10, atol=1e-10)


# ------------------------------------------------------------------------------ 2. gradient equality


def leaves(kind: str) -> list[str]:
    names = ["F", "b", "Q", "H", "R", "x0", "P0"]
    if kind != "kf":
        names += ["mp"] + (["Pi"] if kind != "static" else [])
    return names


@pytest.mark.parametrize("update_first", [False, True])
@pytest.mark.parametrize("kind", KINDS)
def test_gradients_equal_eager(kind, update_first, calls):
    p, z = params(kind, 3, 2, 3, B=(4,), T=12, seed=31, grad=True)
    names = leaves(kind)

    f, b0 = make(kind, p)
    nll = negative_log_likelihood(f, b0, z, reduction="sum", update_first=update_first)
    assert calls["used"] == 1  # the likelihood took the kernel
    est = run_filter(f, b0, z, update_first=update_first, record="estimate").belief.mean
    assert calls["used"] == 2
    kernel_loss = nll + 0.01 * (est ** 2).sum()
    kernel = torch.autograd.grad(kernel_loss, [p[k] for k in names])

    f, b0 = make(kind, p)
    ll = run_filter(f, b0, z, update_first=update_first, record=Keep("log_likelihood"), fast_path=False)
    est = run_filter(f, b0, z, update_first=update_first, record="estimate", fast_path=False).belief.mean
    eager_loss = -ll.log_likelihood.sum() + 0.01 * (est ** 2).sum()
    eager = torch.autograd.grad(eager_loss, [p[k] for k in names])
    assert calls["used"] == 2

    assert_close(kernel_loss, eager_loss, rtol=1e-12, atol=1e-12)
    for name, gk, ge in zip(names, kernel, eager):
        if name in ("Q", "R", "P0"):
            assert torch.equal(gk, gk.mT), f"the kernel's gradient of {name} is not symmetric"
            gk, ge = sym(gk), sym(ge)
        scale = 1.0 + float(ge.abs().max())
        assert_close(gk, ge, rtol=1e-9, atol=1e-10 * scale, msg=lambda s, name=name: f"{name}: {s}")
        assert torch.isfinite(gk).all()


@pytest.mark.parametrize("kind", KINDS)
def test_gradients_of_filtered_covariances_equal_eager(kind, calls):
    """A loss of the filtered covariances and mode probabilities (the reverse pass's ``P`` and
    ``logmu`` adjoints), through ``Keep("belief")``."""
    p, z = params(kind, 2, 2, 2, B=(3,), T=8, seed=32, grad=True)
    names = leaves(kind)
    weights = torch.linspace(0.5, 1.5, 8)

    def loss(fast_path):
        f, b0 = make(kind, p)
        traj = run_filter(f, b0, z, record=Keep("belief", "log_likelihood"), fast_path=fast_path)
        est = traj.belief.estimate()
        out = (weights[:, None, None, None] * est.cov).sum() + traj.log_likelihood.sum()
        if kind != "kf":
            out = out + (traj.belief.mode_log_probs[..., 0] * weights[:, None]).sum()
        return out

    gk = torch.autograd.grad(loss(True), [p[k] for k in names])
    assert calls["used"] == 1
    ge = torch.autograd.grad(loss(False), [p[k] for k in names])
    for name, a, e in zip(names, gk, ge):
        if name in ("Q", "R", "P0"):
            a, e = sym(a), sym(e)
        assert_close(a, e, rtol=1e-9, atol=1e-10 * (1 + float(e.abs().max())), msg=lambda s, name=name: f"{name}: {s}")


# ------------------------------------------------------------------------------ 3. finite differences


@pytest.mark.parametrize("kind,update_first", [("kf", False), ("imm", False), ("gpb1", True), ("static", False),
                                               ("imm", True)])
def test_gradcheck(kind, update_first, calls):
    """The kernel's reverse pass against finite differences of the kernel itself (symmetric matrices
    parametrised as ``(X + X^T) / 2``, the transition and mode probabilities as softmaxes)."""
    n, m, M = 2, 2, 2
    base, z = params(kind, n, m, M, B=(2,), T=8, seed=41)
    names = [k for k in ("F", "b", "Q", "H", "R", "x0", "P0", "mp", "Pi") if k in base]
    inputs = []
    for k in names:
        t = base[k]
        if k in ("mp", "Pi"):
            t = t.log()
        inputs.append(t.detach().clone().requires_grad_())

    def fn(*xs):
        p = dict(zip(names, xs))
        for k in ("Q", "R", "P0"):
            p[k] = sym(p[k])
        for k in ("mp", "Pi"):
            if k in p:
                p[k] = torch.softmax(p[k], -1)
        f, b0 = make(kind, p)
        traj = run_filter(f, b0, z, update_first=update_first, record="estimate", fast_path=True)
        return traj.log_likelihood, traj.belief.mean, traj.belief.cov

    assert torch.autograd.gradcheck(fn, tuple(inputs), eps=1e-6, atol=1e-6, rtol=1e-5)
    assert calls["used"] > 0 and calls["used"] == calls["tried"]


# ------------------------------------------------------------------------------- 4. learnable models


def test_learnable_imm_gradients_equal_eager(calls):
    n, m, M = 2, 2, 3
    p, z = params("imm", n, m, M, B=(3,), T=10, seed=51)
    Q = torch.diag_embed(0.1 + p["Q"].diagonal(dim1=-2, dim2=-1))  # log_diagonal: a diagonal start
    motion = LinearMotion(p["F"].clone(), Q, offset=p["b"])
    sensor = LinearMeasurement(p["H"], p["R"][0])
    learnable_noise(motion, "Q", "log_diagonal")
    learnable_noise(sensor, "R", "cholesky")
    imm = IMM(KalmanFilter(motion, sensor), ModeTransition(p["Pi"], learnable=True))
    params_ = list(imm.parameters())
    assert len(params_) == 3  # log Q, the factor of R, the transition's logits
    b0 = imm.initial_belief(GaussianBelief(p["x0"], p["P0"]), p["mp"])

    kernel = torch.autograd.grad(negative_log_likelihood(imm, b0, z, reduction="sum"), params_)
    assert calls["used"] == 1
    traj = run_filter(imm, b0, z, record=Keep("log_likelihood"), fast_path=False)
    eager = torch.autograd.grad(-traj.log_likelihood.sum(), params_)
    assert calls["used"] == 1
    for gk, ge in zip(kernel, eager):
        assert_close(gk, ge, rtol=1e-9, atol=1e-10 * (1 + float(ge.abs().max())))
        assert ge.abs().max() > 0


def test_learnable_local_level_gradients_equal_eager(calls):
    """experiments/realdata.py's ``local_level(learnable=True)``: one state, ``log q``, ``log r``."""
    one = torch.ones(1, 1)
    motion = LinearMotion(one, torch.full((1, 1), 0.5))
    sensor = LinearMeasurement(one, torch.full((1, 1), 2.0))
    learnable_noise(motion, "Q", "log_diagonal")
    learnable_noise(sensor, "R", "log_diagonal")
    kf = KalmanFilter(motion, sensor)
    g = torch.Generator().manual_seed(52)
    y = torch.cumsum(torch.randn(40, 1, generator=g), 0) + torch.randn(40, 1, generator=g)
    y[10:13] = float("nan")
    b0 = GaussianBelief(torch.zeros(1), torch.full((1, 1), 10.0))
    params_ = list(kf.parameters())
    kernel = torch.autograd.grad(negative_log_likelihood(kf, b0, y, reduction="sum", update_first=True), params_)
    assert calls["used"] == 1
    traj = run_filter(kf, b0, y, record=Keep("log_likelihood"), update_first=True, fast_path=False)
    eager = torch.autograd.grad(-traj.log_likelihood.sum(), params_)
    for gk, ge in zip(kernel, eager):
        assert_close(gk, ge, rtol=1e-10, atol=1e-12)


# -------------------------------------------------------------------------------- 5. automatic choice


@pytest.mark.parametrize("batch", [(1,), ()], ids=str)
@pytest.mark.parametrize("kind", KINDS)
def test_default_takes_the_kernel_for_one_run(kind, batch, calls):
    p, z = params(kind, B=batch, seed=61)
    f, b0 = make(kind, p)
    auto = run_filter(f, b0, z)
    assert calls == {"tried": 1, "used": 1}
    assert_same(auto, run_filter(f, b0, z, fast_path=False))


@pytest.mark.parametrize("kind", ["kf", "imm"])
def test_long_run_rule(kind, calls, monkeypatch):
    """The default takes the kernel from LONG_RUN steps x runs on, whatever the process ran before
    (Numba is loaded here); shorter runs step eagerly, with the same results to rounding."""
    monkeypatch.setattr(linear, "LONG_RUN", 40)
    p, z = params(kind, B=(4,), T=10, seed=64)  # 10 x 4 = 40: the kernel
    f, b0 = make(kind, p)
    with torch.no_grad():
        assert_same(run_filter(f, b0, z), run_filter(f, b0, z, fast_path=False))
    assert calls == {"tried": 1, "used": 1}
    with torch.no_grad():
        short = run_filter(f, b0, z[:9])  # 9 x 4 = 36: the steps, bit for bit
        eager = run_filter(f, b0, z[:9], fast_path=False)
    assert calls["tried"] == 1
    for got, want in zip(fields(short), fields(eager)):
        if isinstance(got, torch.Tensor):
            assert torch.equal(got.nan_to_num(), want.nan_to_num())


def _assert_declines(calls, f, b0, z, **kwargs):
    """The default runs without the kernel and gives the eager results; ``fast_path=True`` raises a
    ValueError naming ``fast_path``."""
    with torch.no_grad():
        auto = run_filter(f, b0, z, **kwargs)
        eager = run_filter(f, b0, z, fast_path=False, **kwargs)
    assert calls["tried"] == 0
    assert_same(auto, eager)
    return auto


def test_more_runs_than_max_runs_declines(calls):
    runs = linear.MAX_RUNS + 1
    assert runs <= 4096  # (the test builds that many runs)
    for kind in ("kf", "imm"):
        p, z = params(kind, 2, 2, 2, B=(runs,), T=8, seed=62)
        f, b0 = make(kind, p)
        _assert_declines(calls, f, b0, z)
        # forced, the kernel takes it
        with torch.no_grad():
            forced = run_filter(f, b0, z, fast_path=True)
            assert calls["used"] == 1
            assert_same(forced, run_filter(f, b0, z, fast_path=False))
        calls["used"] = calls["tried"] = 0
    p, z = params("kf", 2, 2, B=(linear.MAX_RUNS,), T=8, seed=62)
    with torch.no_grad():
        run_filter(*make("kf", p), z)
    assert calls["used"] == 1


def _with_inputs(kind: str, p: dict, k: int = 2, seed: int = 0, grad: bool = False):
    """The filter of ``make(kind, p)`` with an input matrix ``G`` (one per mode for a bank) and ``G``."""
    g = torch.Generator().manual_seed(seed)
    n = p["F"].shape[-1]
    G = torch.randn(*p["F"].shape[:-2], n, k, generator=g, dtype=p["F"].dtype).requires_grad_(grad)
    kf = KalmanFilter(LinearMotion(p["F"], p["Q"], offset=p["b"], input_matrix=G), LinearMeasurement(p["H"], p["R"]))
    belief0 = GaussianBelief(p["x0"], p["P0"])
    if kind == "kf":
        return kf, belief0, G
    f = {"imm": lambda: IMM(kf, p["Pi"]), "gpb1": lambda: GPB1(kf, p["Pi"]),
         "static": lambda: StaticMM(kf, p["mp"].shape[-1])}[kind]()
    return f, f.initial_belief(belief0, p["mp"]), G


@pytest.mark.parametrize("update_first", [False, True])
@pytest.mark.parametrize("kind", KINDS)
def test_controls_equal_eager(kind, update_first, calls):
    """Controls through the motion's input matrix (``F x + b + G u_t``; issue 45: regressors): the kernel
    takes them and equals the eager steps, per-run controls and controls shared by every run."""
    p, z = params(kind, 3, 2, 3, B=(4,), seed=63 + KINDS.index(kind))
    f, b0, _ = _with_inputs(kind, p)
    g = torch.Generator().manual_seed(1)
    for u in (torch.randn(10, 4, 2, generator=g, dtype=torch.float64),
              torch.randn(10, 1, 2, generator=g, dtype=torch.float64)):
        with torch.no_grad():
            fast = run_filter(f, b0, z, controls=u, update_first=update_first, fast_path=True)
            eager = run_filter(f, b0, z, controls=u, update_first=update_first, fast_path=False)
        assert_same(fast, eager)
    assert calls["used"] == 2
    # the input matrix without controls: no input term, as in the eager steps
    with torch.no_grad():
        assert_same(run_filter(f, b0, z, fast_path=True), run_filter(f, b0, z, fast_path=False))


@pytest.mark.parametrize("kind", ["kf", "imm"])
def test_controls_gradients_equal_eager(kind, calls):
    """The likelihood's gradient in the input matrix, the controls and the other models through the
    kernel's reverse pass equals autograd's through the eager steps."""
    p, z = params(kind, 3, 2, 2, B=(3,), seed=70, grad=True)
    f, b0, G = _with_inputs(kind, p, grad=True)
    u = torch.randn(10, 3, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64, requires_grad=True)
    wrt = [G, u, p["F"], p["b"], p["Q"], p["R"]]
    fast = run_filter(f, b0, z, controls=u, fast_path=True, record=Keep("log_likelihood")).log_likelihood.sum()
    assert calls["used"] == 1
    eager = run_filter(f, b0, z, controls=u, fast_path=False).log_likelihood.sum()
    assert_close(fast, eager, **TIGHT)
    for i, (a, b) in enumerate(zip(torch.autograd.grad(fast, wrt), torch.autograd.grad(eager, wrt))):
        # (Q and R: the kernel's adjoints are the symmetric part of autograd's, module docstring)
        assert_close(a, sym(b) if i >= 4 else b, **TIGHT)


def test_controls_without_an_input_matrix_decline(calls):
    """Controls for a motion without an input matrix: the kernel declines, and the eager steps name
    ``u`` (as they do without kernels)."""
    p, z = params("kf", 3, 2, B=(4,), seed=63)
    kf, b0 = make("kf", p)
    u = torch.randn(10, 4, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with pytest.raises(ValueError, match="fast_path: no fast path .*controls, but the motion has no input matrix"):
        run_filter(kf, b0, z, controls=u, fast_path=True)
    with pytest.raises(ValueError, match="^u: this LinearMotion has no input_matrix"):
        run_filter(kf, b0, z, controls=u)
    assert calls["tried"] == 0


@pytest.mark.parametrize("kind", ["kf", "imm"])
def test_per_step_motions_decline(kind, calls):
    p, z = params(kind, seed=64)
    f, b0 = make(kind, p)
    motion = f.motion if kind == "kf" else f.bank.filter.motion
    motions = [motion] * z.shape[0]
    _assert_declines(calls, f, b0, z, motions=motions)
    with pytest.raises(ValueError, match="fast_path"):
        run_filter(f, b0, z, motions=motions, fast_path=True)


def test_joseph_form_declines(calls):
    p, z = params("kf", seed=65)
    f, b0 = make("kf", p, joseph=True)
    auto = _assert_declines(calls, f, b0, z)
    with pytest.raises(ValueError, match="fast_path"):
        run_filter(f, b0, z, fast_path=True)
    # (and the Joseph form is the same filter: the kernel's standard form agrees)
    with torch.no_grad():
        standard = run_filter(*make("kf", p), z, fast_path=True)
    assert_close(standard.log_likelihood, auto.log_likelihood, rtol=1e-9, atol=1e-9)


def test_extended_kalman_filter_declines(calls):
    p, z = params("kf", seed=66)
    ekf = ExtendedKalmanFilter(LinearMotion(p["F"], p["Q"], offset=p["b"]), LinearMeasurement(p["H"], p["R"]))
    b0 = GaussianBelief(p["x0"], p["P0"])
    _assert_declines(calls, ekf, b0, z)
    with pytest.raises(ValueError, match="fast_path"):
        run_filter(ekf, b0, z, fast_path=True)


def test_gpb2_declines(calls):
    p, z = params("imm", seed=67)
    kf, b0 = make("kf", p)  # (mode-bank models: the bank of the GPB2)
    gpb2 = GPB2(kf, p["Pi"])
    b0 = gpb2.initial_belief(b0, p["mp"])
    _assert_declines(calls, gpb2, b0, z)
    with pytest.raises(ValueError, match="fast_path"):
        run_filter(gpb2, b0, z, fast_path=True)


class SteppedIMM(IMM):
    """An IMM whose step is its own (here the same, but the kernel cannot know)."""

    def step(self, belief, z, **kwargs):
        return super().step(belief, z, **kwargs)


def test_imm_subclass_overriding_step_declines(calls):
    p, z = params("imm", seed=68)
    f, _ = make("imm", p)
    sub = SteppedIMM(f.bank, p["Pi"])
    b0 = sub.initial_belief(GaussianBelief(p["x0"], p["P0"]), p["mp"])
    _assert_declines(calls, sub, b0, z)
    with pytest.raises(ValueError, match="fast_path"):
        run_filter(sub, b0, z, fast_path=True)

    class Plain(IMM):  # a subclass that keeps the steps stays in the family
        pass

    plain = Plain(f.bank, p["Pi"])
    with torch.no_grad():
        run_filter(plain, b0, z)
    assert calls["used"] == 1


# ----------------------------------------------------------------------------------- 6. fallback


@pytest.mark.parametrize("update_first", [False, True])
@pytest.mark.parametrize("kind", ["kf", "imm"])
def test_singular_innovation_falls_back_to_eager(kind, update_first, calls):
    """R = 0 and P0 = 0: the first update's S = H P0 H^T + R = 0 (update_first; without it Q = 0 too,
    so that the prediction P = F P0 F^T + Q is 0)."""
    p, z = params(kind, 2, 2, 2, B=(3,), seed=71, missing=False)
    for k in ("R", "P0") if update_first else ("Q", "R", "P0"):
        p[k] = torch.zeros_like(p[k])
    f, b0 = make(kind, p)
    with torch.no_grad():
        auto = run_filter(f, b0, z, update_first=update_first)
        eager = run_filter(f, b0, z, update_first=update_first, fast_path=False)
    assert calls["tried"] == 1 and calls["used"] == 0  # declined at run time
    assert_same(auto, eager)
    singular = auto.extras["singular"] if kind == "kf" else auto.extras["modes"]["singular"]
    assert singular.dtype == torch.bool and bool(singular.any())


# --------------------------------------------------------------------------- 7. autograd and record


@pytest.mark.parametrize("kind", KINDS)
def test_autograd_with_every_field_declines(kind, calls):
    p, z = params(kind, seed=72, grad=True)
    f, b0 = make(kind, p)
    traj = run_filter(f, b0, z)
    assert calls["tried"] == 0
    assert traj.log_likelihood.grad_fn is not None and "View" not in type(traj.log_likelihood.grad_fn).__name__
    prior_mean = traj.prior.mean if kind == "kf" else traj.prior.components.mean
    assert prior_mean.requires_grad and traj.innovation.requires_grad and traj.innovation_cov.requires_grad
    eager = run_filter(f, b0, z, fast_path=False)
    assert_same(traj, eager)
    # a record that keeps the prior declines as well; one of the likelihood and beliefs does not
    run_filter(f, b0, z, record=Keep("log_likelihood", "prior"))
    assert calls["tried"] == 0
    kept = run_filter(f, b0, z, record=Keep("log_likelihood", "belief"))
    assert calls["used"] == 1 and kept.log_likelihood.requires_grad
    # without a graph every field comes from the kernel, non-differentiable
    with torch.no_grad():
        run_filter(f, b0, z)
    assert calls["used"] == 2


def test_autograd_forced_with_every_field(calls):
    """``fast_path=True`` with autograd and every field: never a non-differentiable prior."""
    p, z = params("kf", seed=73, grad=True)
    f, b0 = make("kf", p)
    try:
        traj = run_filter(f, b0, z, fast_path=True)
    except ValueError as error:
        assert "fast_path" in str(error)
        return
    assert calls["used"] == 0
    assert traj.prior.mean.requires_grad and traj.innovation.requires_grad


# ---------------------------------------------------------------------------------------- 8. float32


def test_float32_forward_equals_eager(calls):
    p, z = params("imm", 3, 2, 3, B=(4,), seed=81, dtype=torch.float32)
    f, b0 = make("imm", p)
    with torch.no_grad():
        fast = run_filter(f, b0, z, fast_path=True)
        eager = run_filter(f, b0, z, fast_path=False)
    assert calls["used"] == 1
    assert fast.log_likelihood.dtype == torch.float32
    assert_same(fast, eager, rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------------------------------- 9. Keep


def test_keep_rejects_unknown_fields():
    with pytest.raises(ValueError, match="fields"):
        Keep("log_likelihood", "beleif")


@pytest.mark.parametrize("kind", ["kf", "imm"])
def test_keep_log_likelihood_on_the_kernel(kind, calls):
    p, z = params(kind, seed=91, grad=True)
    f, b0 = make(kind, p)
    traj = run_filter(f, b0, z, record=Keep("log_likelihood"))
    assert calls["used"] == 1
    assert traj.belief is None and traj.prior is None and traj.innovation is None
    assert traj.innovation_cov is None and traj.extras is None
    eager = run_filter(f, b0, z, record=Keep("log_likelihood"), fast_path=False)
    assert_same(traj, eager)
    assert traj.log_likelihood.requires_grad
    detached = run_filter(f, b0, z, record=Keep("log_likelihood", "belief", detach=True))
    assert calls["used"] == 2
    mean = detached.belief.mean if kind == "kf" else detached.belief.components.mean
    assert not mean.requires_grad and detached.log_likelihood.requires_grad
    assert_close(detached.final_belief.mean if kind == "kf" else detached.final_belief.components.mean,
                 run_filter(f, b0, z, fast_path=False).final_belief.mean if kind == "kf"
                 else run_filter(f, b0, z, fast_path=False).final_belief.components.mean, **TIGHT)


# ------------------------------------------------------------------------------ smoothers (plan_smooth)


@pytest.mark.parametrize("kind", ["kf", "imm", "gpb1"])
def test_kernel_smoothers_equal_the_eager_smoothers(kind, monkeypatch):
    """Kim's smoother of IMM/GPB1 runs and RTS of Kalman runs through the kernel equal torchmm.smooth's
    eager steps (every kernel switched off), with missing data and a trajectory from the steps."""
    import torchmm.kernels as kernels
    from torchmm import smooth

    p, z = params(kind, seed=71)
    f, b0 = make(kind, p)
    smoothed_by = []
    original = linear.load

    def counting_load():  # the smoother's run() loads the loops once per call
        smoothed_by.append(True)
        return original()

    with torch.no_grad():
        with kernels.switched_off("linear_gaussian"), kernels.switched_off("batch_last"):
            traj = run_filter(f, b0, z)
            eager = smooth(traj) if kind == "kf" else smooth(traj, method="kim")
        monkeypatch.setattr(linear, "load", counting_load)
        kernel = smooth(traj) if kind == "kf" else smooth(traj, method="kim")
    assert smoothed_by, "the kernel smoother did not run"
    got, want = pytree.tree_leaves(kernel.belief), pytree.tree_leaves(eager.belief)
    assert len(got) == len(want)
    for a, e in zip(got, want):
        assert_close(a, e, **TIGHT)
    # the smoother changes every step but the last (which is the filter's)
    assert not torch.allclose(gaussian(kernel.belief).mean[0], gaussian(traj.belief).mean[0])


def test_kernel_kim_takes_log_space_where_probabilities_are_tiny(monkeypatch):
    """Kim's compiled loop weighs the modes in linear space where a step's log-probabilities lie within 700
    of their largest and in log space elsewhere (issue 47): regimes 60 noise standard deviations apart make
    probabilities of exp(-1800) at most steps, moderate ones where the data sit between; both paths equal
    the eager smoother (every kernel off), the smoothed log-probabilities of the tiny ones included."""
    import torchmm.kernels as kernels
    from experiments.realdata import fedfunds_imm
    from torchmm import smooth

    y = torch.zeros(60, 1, dtype=torch.float64)
    y[20:30] = 60.0
    y[30:36] = torch.linspace(45.0, 15.0, 6, dtype=torch.float64).unsqueeze(-1)  # between: moderate weights
    y += 0.3 * torch.randn(60, 1, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    imm, b0 = fedfunds_imm([0.0, 60.0], [1.0, 1.0], [[0.95, 0.05], [0.1, 0.9]])
    with torch.no_grad():
        with kernels.switched_off("linear_gaussian"), kernels.switched_off("batch_last"):
            traj = run_filter(imm, b0, y)
            eager = smooth(traj, method="kim").belief
        loaded = []
        original = linear.load
        monkeypatch.setattr(linear, "load", lambda: loaded.append(True) or original())
        kernel = smooth(traj, method="kim").belief
    assert loaded, "the kernel smoother did not run"
    logs = eager.mode_log_probs
    assert bool((logs.amin(-1) < -700).sum() > 20) and bool(((logs.amin(-1) > -700) & (logs.amin(-1) < -1)).any())
    assert_close(kernel.mode_log_probs, eager.mode_log_probs, **TIGHT)
    assert_close(kernel.components.mean, eager.components.mean, **TIGHT)
    assert_close(kernel.components.cov, eager.components.cov, **TIGHT)
