"""Multi-rate IMMs (paper 000): IMM-TF / IF-TF, IMM-SU, IMM-FU, VSIMM.

References: a hand-written float64 NumPy IMM-TF (tests/reference/transfer_numpy.py), the NumPy IMM,
joint-Gaussian conditioning for the smoothing step, autograd for the influence function, an IMM
with a stacked sensor for IMM-SU, and per-run loops for batching.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch

from tests.conftest import assert_symmetric_psd, random_psd, random_system, random_transition
from tests.reference import mm_numpy, transfer_numpy
from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    LinearMeasurement,
    LinearMotion,
    PositionMeasurement,
    UnscentedKalmanFilter,
    rts_smoother,
    run_filter,
)
from torchmm.multimodel import (
    FusionIMM,
    InfluenceGate,
    MultiRate,
    SourceModeVSIMM,
    SourceUpdateIMM,
    TransferIMM,
    influence_value,
)

close = partial(torch.testing.assert_close, rtol=1e-9, atol=1e-9)
P000 = [[0.50, 0.25, 0.25], [0.25, 0.50, 0.25], [0.25, 0.25, 0.50]]


def paper_setup(runs=6, steps=30, ratio=0.6, RS=10.0, seed=0, dtype=torch.float64):
    """The paper-000 scenario (small): bank filter, transition, source sensor, prior, data."""
    motion = ConstantVelocity(1, q=1.0, acceleration=torch.tensor([[0.25], [0.0], [-0.25]], dtype=dtype), dtype=dtype)
    sensor = PositionMeasurement(2, [0], torch.tensor(100.0, dtype=dtype))
    source = PositionMeasurement(2, [0], torch.tensor(RS, dtype=dtype))
    P = torch.tensor(P000, dtype=dtype)
    prior = GaussianBelief(torch.tensor([10.0, 10.0], dtype=dtype), torch.tensor([[100.0, 1.0], [1.0, 100.0]], dtype=dtype))
    from torchmm.simulate import bernoulli_mask, simulate_jump_system, simulate_measurements

    g = torch.Generator().manual_seed(seed)
    truth = simulate_jump_system(motion, P, prior, steps, (runs,), generator=g)
    y = simulate_measurements(sensor, truth.states, generator=g)
    mask = bernoulli_mask(steps, (runs,), ratio, generator=g)
    ys = simulate_measurements(source, truth.states, available=mask, generator=g)
    return KalmanFilter(motion, sensor), P, source, prior.expand(runs), MultiRate(y, ys), truth


def all_estimators(kf, P, source):
    return {
        "IMM-TF": TransferIMM(kf, P, source),
        "IF-TF": TransferIMM(kf, P, source, gate=InfluenceGate()),
        "IMM-TF corrected": TransferIMM(kf, P, source, mode_likelihood="corrected", smoothing_reference="mixed"),
        "IMM-SU": SourceUpdateIMM(kf, P, source),
        "IMM-FU": FusionIMM(kf, P, source),
        "VSIMM": SourceModeVSIMM(kf, P, source, extra_model=1),
    }


def _run(f, prior, z, **options):
    return run_filter(f, f.initial_belief(prior), z, **options)


# ---------------------------------------------------------------------------------------------
# IMM-TF against the NumPy reference
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_transfer_imm_matches_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    n, m, M, steps = 3, 1, 3, 25
    base = random_system(n, m, rng)
    models = []
    for _ in range(M):
        F = base.F + 0.2 * rng.normal(size=(n, n))
        F = 0.95 * F / max(1.0, np.abs(np.linalg.eigvals(F)).max())
        models.append((F, 2.0 * rng.normal(size=n), random_psd(n, rng, 0.5)))
    Hs, Rs = base.H + 0.1 * rng.normal(size=(m, n)), 0.3 * base.R
    Pi = random_transition(M, rng)
    _, zs = base.simulate(steps, rng)
    zs_source = zs + rng.normal(size=zs.shape)
    zs_source[rng.uniform(size=steps) > 0.5] = np.nan
    mu0 = np.full(M, 1 / M)
    ref_x, ref_P, ref_mu = transfer_numpy.imm_tf(models, base.H, base.R, Hs, Rs, Pi, base.x0, base.P0, mu0, zs,
                                                 zs_source)
    motion = LinearMotion(torch.tensor(np.stack([f for f, _, _ in models])), torch.tensor(np.stack([q for _, _, q in models])),
                          offset=torch.tensor(np.stack([b for _, b, _ in models])))
    tf = TransferIMM(KalmanFilter(motion, LinearMeasurement(torch.tensor(base.H), torch.tensor(base.R))),
                     torch.tensor(Pi), LinearMeasurement(torch.tensor(Hs), torch.tensor(Rs)))
    traj = _run(tf, GaussianBelief(torch.tensor(base.x0), torch.tensor(base.P0)), MultiRate(torch.tensor(zs), torch.tensor(zs_source)))
    est = traj.estimate()
    close(est.mean, torch.tensor(ref_x), rtol=1e-8, atol=1e-8)
    close(est.cov, torch.tensor(ref_P), rtol=1e-8, atol=1e-8)
    close(traj.belief.mode_probs, torch.tensor(ref_mu), rtol=1e-8, atol=1e-10)
    present = torch.tensor(np.isfinite(zs_source).all(-1))
    assert torch.equal(traj.extras["source_present"], present)


def test_gamma_zero_equals_imm_exactly():
    kf, P, source, prior, z, _ = paper_setup()
    imm = IMM(kf, P)  # its batch-first steps, which IMM-TF shares (the default fast path equals them to rounding)
    imm_traj = run_filter(imm, imm.initial_belief(prior), z.target, fast_path=False)
    no_source = MultiRate(z.target, torch.full_like(z.source, torch.nan))
    for name, f in all_estimators(kf, P, source).items():
        # the eager steps: IMM-TF's batch-last kernel (tests/multimodel/test_batch_last_transfer.py)
        # equals them to rounding, as the IMM's kernel equals the IMM's steps
        traj = _run(f, prior, no_source, fast_path=False)
        if name.startswith(("IMM-TF", "IF-TF")):
            close(_run(f, prior, no_source).estimate().mean, imm_traj.estimate().mean, rtol=1e-12, atol=1e-12)
        if name in {"VSIMM", "IMM-SU"}:
            # VSIMM: the renormalised restricted transition matrix; IMM-SU: the skipped source update
            # re-symmetrises the covariance. Equal up to rounding.
            close(traj.estimate().mean, imm_traj.estimate().mean, rtol=1e-12, atol=1e-12)
            close(traj.estimate().cov, imm_traj.estimate().cov, rtol=1e-12, atol=1e-12)
            close(traj.belief.mode_probs[..., :3], imm_traj.belief.mode_probs, rtol=1e-12, atol=1e-14)
            if name == "VSIMM":
                assert bool((traj.belief.mode_probs[..., 3] == 0).all())
            continue
        assert torch.equal(traj.estimate().mean, imm_traj.estimate().mean), name
        assert torch.equal(traj.estimate().cov, imm_traj.estimate().cov), name
        assert torch.equal(traj.belief.mode_log_probs, imm_traj.belief.mode_log_probs), name
        close(traj.log_likelihood, imm_traj.log_likelihood)


def test_gamma_zero_matches_numpy_imm():
    kf, P, source, prior, z, _ = paper_setup(runs=1, steps=20)
    models = [(kf.motion.F.numpy(), kf.motion.offset[j].numpy(), kf.motion.Q.numpy()) for j in range(3)]
    ref_x, _, ref_mu = mm_numpy.imm(models, kf.measurement.H.numpy(), kf.measurement.R.numpy(), np.array(P000),
                                    prior.mean[0].numpy(), prior.cov[0].numpy(), np.full(3, 1 / 3), z.target[:, 0].numpy())
    traj = _run(TransferIMM(kf, P, source), prior, MultiRate(z.target, torch.full_like(z.source, torch.nan)))
    close(traj.estimate().mean[:, 0], torch.tensor(ref_x))
    close(traj.belief.mode_probs[:, 0], torch.tensor(ref_mu))


# ---------------------------------------------------------------------------------------------
# smoothing (13)-(14)
# ---------------------------------------------------------------------------------------------
def test_transfer_smoothing_is_the_rts_step_on_a_two_step_problem():
    """Single mode: (13)-(14) = RTS backward step = p(x_{k-1} | y_S,k) by joint conditioning."""
    rng = np.random.default_rng(3)
    sys_ = random_system(2, 1, rng)
    Hs, Rs = sys_.H + 0.3, 0.2 * sys_.R
    motion = sys_.motion()
    kf = KalmanFilter(motion, sys_.measurement())
    source = LinearMeasurement(torch.tensor(Hs), torch.tensor(Rs))
    tf = TransferIMM(kf, torch.ones(1, 1), source)
    belief0 = sys_.prior()
    y1, _ys1 = torch.tensor(rng.normal(size=(1,))), torch.tensor(rng.normal(size=(1,)))
    step1 = tf.step(tf.initial_belief(belief0), MultiRate(y1, torch.full((1,), torch.nan)))
    filtered = step1.belief.estimate()  # x_{k-1|k-1} (the combined output at k-1)
    y2, ys2 = torch.tensor(rng.normal(size=(1,))), torch.tensor(rng.normal(size=(1,)))
    step2 = tf.step(step1.belief, MultiRate(y2, ys2))
    smoothed = step2.extras["smoothed"].select(-1, 0)

    # the RTS smoother on the two-step sequence (filtered at k-1, source posterior at k)
    kf_source = KalmanFilter(motion, source)
    predicted = kf.predict(filtered)
    source_post = kf_source.update(predicted, ys2).belief
    seq_filtered = GaussianBelief(torch.stack([filtered.mean, source_post.mean]), torch.stack([filtered.cov, source_post.cov]))
    seq_pred = GaussianBelief(torch.stack([filtered.mean, predicted.mean]), torch.stack([filtered.cov, predicted.cov]))
    rts = rts_smoother(motion, seq_filtered, seq_pred)
    close(smoothed.mean, rts.mean[0])
    close(smoothed.cov, rts.cov[0])

    # and the independent oracle: condition x_{k-1} on y_S,k jointly
    mean, cov = transfer_numpy.smoothed_previous(
        filtered.mean.numpy(), filtered.cov.numpy(), sys_.F, sys_.offset, sys_.Q, Hs, Rs,
        predicted.mean.numpy(), predicted.cov.numpy(), ys2.numpy())
    close(smoothed.mean, torch.tensor(mean))
    close(smoothed.cov, torch.tensor(cov))
    # transferred knowledge u_S = H F m (+ offset), in the target sensor's space
    close(step2.extras["transferred_knowledge"][0], torch.tensor(sys_.H @ (sys_.F @ mean + sys_.offset)))


# ---------------------------------------------------------------------------------------------
# influence function (29)-(36)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n,m", [(2, 1), (3, 2)])
def test_influence_value_is_half_the_implicit_derivative_of_the_loss(n, m):
    """(33) = 1/2 (D1): dF/dx (d2F/dx2)^{-1} d2F/dxdy at the estimate, all by autograd."""
    rng = np.random.default_rng(n + m)
    H = torch.tensor(rng.normal(size=(m, n)))
    R = torch.tensor(random_psd(m, rng))
    W = torch.tensor(random_psd(n, rng))
    x_hat, x_prior, y = (torch.tensor(rng.normal(size=s)) for s in (n, n, m))

    def loss(x, yy):  # (29), with W in place of Q_k
        r = yy - H @ x
        d = x - x_prior
        return r @ torch.linalg.solve(R, r) + d @ torch.linalg.solve(W, d)

    grad_x = torch.autograd.functional.jacobian(lambda x: loss(x, y), x_hat)
    hess = torch.autograd.functional.hessian(loss, (x_hat, y))
    d2_xx, d2_xy = hess[0][0], hess[0][1]
    d1 = grad_x @ torch.linalg.solve(d2_xx, d2_xy)  # (m,)
    value = influence_value(x_hat, x_prior, y, H, R, W)
    close(value, 0.5 * d1)
    # equivalently: the derivative of F along the estimate's response to y -> y + rho (31)
    x_star = lambda rho: torch.linalg.solve(torch.linalg.inv(W) + H.T @ torch.linalg.solve(R, H),  # noqa: E731
                                            torch.linalg.solve(W, x_prior) + H.T @ torch.linalg.solve(R, y + rho))
    response = torch.autograd.functional.jacobian(x_star, torch.zeros(m))  # d x*/d rho, (n, m)
    close(value, -0.5 * grad_x @ response)
    # and the closed form -(H (x - x*))^T R^{-1}
    close(value, -torch.linalg.solve(R, H @ (x_hat - x_star(torch.zeros(m)))))


def test_influence_value_batched_and_missing():
    rng = np.random.default_rng(0)
    H = torch.tensor(rng.normal(size=(1, 2))).expand(5, 1, 2)
    R = torch.eye(1, dtype=torch.float64).expand(5, 1, 1)
    W = torch.tensor(random_psd(2, rng)).expand(5, 2, 2)
    x, xp, y = torch.randn(5, 2), torch.randn(5, 2), torch.randn(5, 1)
    y[2] = torch.nan
    batched = influence_value(x, xp, y, H, R, W)
    assert batched.shape == (5, 1)
    assert batched[2].item() == 0.0
    for b in (0, 1, 3, 4):
        close(batched[b], influence_value(x[b], xp[b], y[b], H[b], R[b], W[b]))


def test_influence_value_of_a_partly_missing_datum_with_a_correlated_R():
    """(33)-(36) over the observed components only (a NumPy transcription with explicit inverses): with a
    correlated R the full inverse mixed the missing row's shift into the observed one (0.1928 for 0.0988)."""
    rng = np.random.default_rng(0)
    H, R = rng.normal(size=(2, 3)), np.array([[4.0, 3.0], [3.0, 9.0]])
    A = rng.normal(size=(3, 3))
    W = A @ A.T + np.eye(3)
    x, xm = rng.normal(size=3), rng.normal(size=3)
    for y in (np.array([0.7, np.nan]), np.array([np.nan, -0.4]), np.array([0.7, -0.4])):
        got = influence_value(*(torch.tensor(a) for a in (x, xm, y, H, R, W))).numpy()
        o = np.isfinite(y)
        Ho, Ri, Wi = H[o], np.linalg.inv(R[np.ix_(o, o)]), np.linalg.inv(W)
        Psi = Wi @ (x - xm) - Ho.T @ Ri @ (y[o] - Ho @ x)
        want = -(Psi @ np.linalg.inv(Wi + Ho.T @ Ri @ Ho) @ Ho.T @ Ri)
        np.testing.assert_allclose(got[o], want, rtol=1e-10, atol=1e-12)
        assert (got[~o] == 0).all()


def test_if_tf_gate_rejects_an_uninformative_source():
    """With R_S >> R the transfer only pulls the estimate back: L . nu >= 0 at almost every step."""
    kf, P, source, prior, z, truth = paper_setup(runs=50, steps=60, RS=1e6)
    traj = _run(TransferIMM(kf, P, source, gate=InfluenceGate()), prior, z)
    present = traj.extras["source_present"]
    used = traj.extras["transfer_used"]
    assert bool((used <= present).all())
    assert used.double().sum() <= 0.05 * present.double().sum()
    # with an informative source the gate keeps a substantial share of the transfers
    kf, P, source, prior, z, truth = paper_setup(runs=50, steps=60, RS=1.0)
    traj = _run(TransferIMM(kf, P, source, gate=InfluenceGate()), prior, z)
    share = traj.extras["transfer_used"].double().sum() / traj.extras["source_present"].double().sum()
    assert 0.2 < share < 0.9


def assert_gated_steps(traj, gated, belief0, z, tol=1e-12):
    """Each step of an IF-TF trajectory, from its own previous belief: where ``transfer_used`` the step of
    the same IMM-TF without a gate, elsewhere the plain IMM step (a rejected transfer is no transfer)."""
    imm, ungated = IMM(gated.bank, gated.transition), TransferIMM(
        gated.bank, gated.transition, gated.source, smoothing_reference=gated.smoothing_reference,
        mode_likelihood=gated.mode_likelihood)
    previous = belief0
    for k in range(z.target.shape[0]):
        plain = imm.step(previous, z.target[k])
        transfer = ungated.step(previous, MultiRate(z.target[k], z.source[k]))
        used = traj.extras["transfer_used"][k]
        want_mu = torch.where(used[:, None], transfer.belief.mode_log_probs, plain.belief.mode_log_probs)
        close(traj.belief.mode_log_probs[k], want_mu, rtol=tol, atol=tol)
        mine, tf_step, imm_step = traj.belief.components, transfer.belief.components, plain.belief.components
        for got, a, b in [(mine.mean[k], tf_step.mean, imm_step.mean), (mine.cov[k], tf_step.cov, imm_step.cov),
                          (traj.log_likelihood[k], transfer.log_likelihood, plain.log_likelihood)]:
            close(got, torch.where(used.reshape(used.shape + (1,) * (a.dim() - 1)), a, b), rtol=tol, atol=tol)
        previous = traj.belief[k]


@pytest.mark.parametrize("likelihood", ["prior", "corrected"])
def test_a_rejected_transfer_is_the_imm_step(likelihood):
    """IF-TF's gate "filters out" a harmful source datum (paper 000, sec. 3; docs/reproduction.md): with
    either mode likelihood a rejected step is the plain IMM step, its mode probabilities and likelihood
    too."""
    kf, P, source, prior, z, _ = paper_setup(runs=6, steps=25)
    imm = IMM(kf, P)
    imm_traj = run_filter(imm, imm.initial_belief(prior), z.target, fast_path=False)
    never = TransferIMM(kf, P, source, mode_likelihood=likelihood, gate=InfluenceGate(threshold=-1e300))
    traj = _run(never, prior, z, fast_path=False)
    assert not bool(traj.extras["transfer_used"].any()) and bool(traj.extras["source_present"].any())
    close(traj.estimate().mean, imm_traj.estimate().mean, rtol=1e-12, atol=1e-12)
    close(traj.belief.mode_log_probs, imm_traj.belief.mode_log_probs, rtol=1e-12, atol=1e-12)
    close(traj.log_likelihood, imm_traj.log_likelihood, rtol=1e-12, atol=1e-12)
    gated = TransferIMM(kf, P, source, mode_likelihood=likelihood, gate=InfluenceGate())  # rejects some
    traj = _run(gated, prior, z, fast_path=False)
    present, used = traj.extras["source_present"], traj.extras["transfer_used"]
    assert bool(used.any()) and bool((present & ~used).any())
    assert_gated_steps(traj, gated, gated.initial_belief(prior), z)


def test_influence_gate_validation():
    with pytest.raises(ValueError, match="weight"):
        InfluenceGate(weight="hessian")
    kf, P, source, prior, z, _ = paper_setup(runs=2, steps=3)
    with pytest.raises(ValueError, match="gate"):
        TransferIMM(kf, P, source, gate=InfluenceGate(mode=5))
    with pytest.raises(ValueError, match="gate.weight: process needs a non-singular"):  # G Q G^T is singular
        TransferIMM(kf, P, source, gate=InfluenceGate(weight="process"))  # refused when built, not at a step


def test_influence_gate_process_weight_with_full_rank_noise():
    kf, P, source, prior, z, _ = paper_setup(runs=3, steps=10)
    motion = LinearMotion(kf.motion.F, torch.eye(2), offset=kf.motion.offset)
    f = TransferIMM(KalmanFilter(motion, kf.measurement), P, source, gate=InfluenceGate(weight="process"))
    traj = _run(f, prior, z)
    assert torch.isfinite(traj.extras["influence"]).all()


# ---------------------------------------------------------------------------------------------
# baselines
# ---------------------------------------------------------------------------------------------
def test_source_update_imm_equals_imm_with_stacked_sensor():
    kf, P, source, prior, z, _ = paper_setup(runs=5, steps=30)
    stacked = LinearMeasurement(torch.cat([source.H, kf.measurement.H]),
                                torch.block_diag(source.R, kf.measurement.R))
    ref = _run(IMM(KalmanFilter(kf.motion, stacked), P), prior, torch.cat([z.source, z.target], -1))
    traj = _run(SourceUpdateIMM(kf, P, source), prior, z)
    close(traj.estimate().mean, ref.estimate().mean)
    close(traj.estimate().cov, ref.estimate().cov)
    close(traj.belief.mode_probs, ref.belief.mode_probs)
    close(traj.log_likelihood, ref.log_likelihood)


def test_fusion_imm_is_information_fusion_of_each_mode():
    kf, P, source, prior, z, _ = paper_setup(runs=4, steps=12)
    fu = FusionIMM(kf, P, source)
    belief = fu.initial_belief(prior)
    for k in range(12):
        out = fu.step(belief, MultiRate(z.target[k], z.source[k]))
        # independent pieces: the target IMM step and the source-only IMM step
        tgt = IMM(kf, P).step(belief.target, z.target[k]).belief
        src = IMM(KalmanFilter(kf.motion, source), P).step(belief.source, z.source[k]).belief.estimate()
        for b in range(4):
            for j in range(3):
                xj, Pj = tgt.components.mean[b, j].numpy(), tgt.components.cov[b, j].numpy()
                if torch.isfinite(z.source[k, b]).all():
                    xs, Ps = src.mean[b].numpy(), src.cov[b].numpy()
                    Pf = np.linalg.inv(np.linalg.inv(Pj) + np.linalg.inv(Ps))
                    xf = Pf @ (np.linalg.solve(Pj, xj) + np.linalg.solve(Ps, xs))
                else:
                    xf, Pf = xj, Pj
                close(out.belief.target.components.mean[b, j], torch.tensor(xf), rtol=1e-8, atol=1e-8)
                close(out.belief.target.components.cov[b, j], torch.tensor(Pf), rtol=1e-8, atol=1e-8)
        close(out.belief.mode_probs, tgt.mode_probs)
        belief = out.belief


def test_vsimm_extra_mode_lifecycle():
    kf, P, source, prior, z, _ = paper_setup(runs=20, steps=40)
    vs = SourceModeVSIMM(kf, P, source, extra_model=1)
    traj = _run(vs, prior, z)
    probs = traj.belief.mode_probs
    close(probs.sum(-1), torch.ones(probs.shape[:-1], dtype=probs.dtype))
    present = traj.extras["source_present"]
    # where a source datum arrives, mode e's predicted probability is p_new = 1/(M + 1)
    prior_e = traj.prior.mode_log_probs[..., 3].exp()
    close(prior_e[present], torch.full_like(prior_e[present], 0.25))
    # mode e is active exactly while its probability is at least drop_below
    active = traj.extras["extra_mode_active"]
    assert bool((probs[..., 3][active] >= 1e-3).all()) and bool((probs[..., 3][~active] == 0).all())
    # before the first source datum of a run, mode e is inactive
    first = present.double().argmax(0)
    for b in range(20):
        assert not bool(active[: first[b], b].any())
    T = vs.extended_transition()
    close(T.sum(-1), torch.ones(4, dtype=T.dtype))


# ---------------------------------------------------------------------------------------------
# properties: batching, NaN, float32, shapes, validation
# ---------------------------------------------------------------------------------------------
def test_batched_equals_per_run():
    kf, P, source, prior, z, _ = paper_setup(runs=4, steps=25)
    for name, f in all_estimators(kf, P, source).items():
        batched = _run(f, prior, z)
        for b in range(4):
            single = _run(f, prior[b : b + 1], MultiRate(z.target[:, b : b + 1], z.source[:, b : b + 1]))
            close(batched.estimate().mean[:, b], single.estimate().mean[:, 0], rtol=1e-10, atol=1e-10)
            close(batched.belief.mode_probs[:, b], single.belief.mode_probs[:, 0], rtol=1e-10, atol=1e-12)


def test_extra_batch_dims_and_shapes():
    kf, P, source, prior, z, _ = paper_setup(runs=6, steps=8)
    z2 = MultiRate(z.target.reshape(8, 2, 3, 1), z.source.reshape(8, 2, 3, 1))
    prior2 = prior.reshape(2, 3)
    for name, f in all_estimators(kf, P, source).items():
        traj = _run(f, prior2, z2)
        est = traj.estimate()
        assert est.mean.shape == (8, 2, 3, 2) and est.cov.shape == (8, 2, 3, 2, 2), name
        flat = _run(f, prior, z).estimate()
        close(est.mean.reshape(8, 6, 2), flat.mean, rtol=1e-10, atol=1e-10)
    out = _run(TransferIMM(kf, P, source), prior2, z2)
    assert out.extras["influence"].shape == (8, 2, 3, 1)
    assert out.extras["transfer_used"].dtype == torch.bool


def test_missing_data_never_gives_nan():
    kf, P, source, prior, z, _ = paper_setup(runs=10, steps=40)
    y = z.target.clone()
    y[5:9, :3] = torch.nan  # target outages too
    y[20, :] = torch.nan
    for name, f in all_estimators(kf, P, source).items():
        traj = _run(f, prior, MultiRate(y, z.source))
        est = traj.estimate()
        assert torch.isfinite(est.mean).all() and torch.isfinite(est.cov).all(), name
        assert torch.isfinite(traj.belief.mode_log_probs.exp()).all(), name
        assert torch.isfinite(traj.log_likelihood).all(), name
        assert_symmetric_psd(est.cov[-1], tol=1e-7)


def test_float32_runs_and_stays_finite():
    kf, P, source, prior, z, truth = paper_setup(runs=50, steps=100, dtype=torch.float32)
    assert z.target.dtype == torch.float32
    for name, f in all_estimators(kf, P, source).items():
        traj = _run(f, prior, z)
        est = traj.estimate()
        assert est.mean.dtype == torch.float32, name
        assert torch.isfinite(est.mean).all() and torch.isfinite(est.cov).all(), name
        err = (est.mean[..., 0] - truth.states[..., 0]).square().mean().sqrt()
        assert err < 20.0, (name, err)  # a working filter (R = 100), not a diverged one


def test_transfer_improves_on_imm_with_accurate_source():
    """Property the paper shows (Table 1): with R_S << R the transfer lowers the position RMSE."""
    kf, P, source, prior, z, truth = paper_setup(runs=200, steps=60, RS=1.0)
    rmse = {}
    for name, f in {"IMM": None, **all_estimators(kf, P, source)}.items():
        traj = _run(IMM(kf, P), prior, z.target) if f is None else _run(f, prior, z)
        rmse[name] = (traj.estimate().mean[..., 0] - truth.states[..., 0]).square().mean().sqrt().item()
    for name in ("IMM-TF", "IF-TF", "IMM-SU", "IMM-FU", "VSIMM"):
        assert rmse[name] < rmse["IMM"], rmse
    assert rmse["IMM-SU"] < rmse["IMM-TF"], rmse  # the Bayes-optimal use of the source datum


def test_validation_errors():
    kf, P, source, prior, z, _ = paper_setup(runs=2, steps=3)
    with pytest.raises(ValueError, match="smoothing_reference"):
        TransferIMM(kf, P, source, smoothing_reference="future")
    with pytest.raises(ValueError, match="mode_likelihood"):
        TransferIMM(kf, P, source, mode_likelihood="elbo")
    with pytest.raises(ValueError, match="source"):
        TransferIMM(kf, P, PositionMeasurement(4, [0], 1.0))
    with pytest.raises(ValueError, match="source: state_dim"):
        SourceUpdateIMM(UnscentedKalmanFilter(kf.motion, kf.measurement), P, PositionMeasurement(4, [0], 1.0))
    f = TransferIMM(kf, P, source)
    with pytest.raises(TypeError, match="z:"):
        f.step(f.initial_belief(prior), z.target[0])
    with pytest.raises(ValueError, match="extra_model"):
        SourceModeVSIMM(kf, P, source, extra_model=3)
    with pytest.raises(ValueError, match="p_ee"):
        SourceModeVSIMM(kf, P, source, p_ee=1.5)


def test_transfer_imm_is_differentiable():
    kf, P, source, prior, z, _ = paper_setup(runs=3, steps=10)
    R = torch.tensor(100.0, dtype=torch.float64, requires_grad=True)
    sensor = PositionMeasurement(2, [0], R)
    f = TransferIMM(KalmanFilter(kf.motion, sensor), P, source)
    traj = _run(f, prior, z)
    traj.log_likelihood.sum().backward()
    assert R.grad is not None and torch.isfinite(R.grad)


def test_simulate_multirate_statistics():
    from torchmm.simulate import simulate_multirate

    target, source = PositionMeasurement(2, [0], 100.0), PositionMeasurement(2, [0], 10.0)
    states = torch.randn(200, 500, 2)
    g = torch.Generator().manual_seed(7)
    z = simulate_multirate(target, source, states, probability=0.3, generator=g)
    present = torch.isfinite(z.source[..., 0])
    n = present.numel()
    assert abs(present.double().mean().item() - 0.3) < 4 * (0.3 * 0.7 / n) ** 0.5
    assert torch.isfinite(z.target).all()
    # noise variances within 4 standard errors (var of a sample variance ~ 2 sigma^4 / n)
    v_t = (z.target[..., 0] - states[..., 0]).var().item()
    v_s = (z.source[..., 0] - states[..., 0])[present].var().item()
    assert abs(v_t - 100.0) < 4 * 100.0 * (2 / n) ** 0.5
    assert abs(v_s - 10.0) < 4 * 10.0 * (2 / present.sum().item()) ** 0.5
    periodic = simulate_multirate(target, source, states, period=4, offset=1, generator=g)
    mask = torch.isfinite(periodic.source[..., 0])
    assert bool(mask[0].all()) and not bool(mask[1:4].any()) and bool(mask[4].all())
    with pytest.raises(ValueError, match="exactly one"):
        simulate_multirate(target, source, states, generator=g)
    with pytest.raises(ValueError, match="exactly one"):
        simulate_multirate(target, source, states, probability=0.5, period=2, generator=g)
