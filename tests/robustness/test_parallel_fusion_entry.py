"""Entry points that skipped the entry checks (issue 29, defect 3): ``torchmm.parallel`` runs
``run_filter``'s checks, ``torchmm.fusion`` validates its tracks and joint covariances. Every error is a
``ValueError`` or ``TypeError`` whose message starts with the argument's name."""

from __future__ import annotations

import pytest
import torch

from torchmm import ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, parallel, run_filter
from torchmm.fusion import fuse, fuse_tracks, fusion_weights
from torchmm.parallel import associative_scan

D = torch.float64


def _system(steps=8, runs=3):
    kf = KalmanFilter(ConstantVelocity(1, q=0.1, dtype=D), PositionMeasurement(2, [0], 1.0, dtype=D))
    z = torch.cumsum(torch.randn(steps, runs, 1, generator=torch.Generator().manual_seed(0), dtype=D), 0)
    belief0 = GaussianBelief(torch.zeros(runs, 2, dtype=D), 4 * torch.eye(2, dtype=D).expand(runs, 2, 2))
    return kf, belief0, z


# -- torchmm.parallel -------------------------------------------------------------------------------

@pytest.mark.parametrize("entry", [parallel.filter, parallel.smooth], ids=["filter", "smooth"])
def test_parallel_entry_points_run_the_entry_checks_of_run_filter(entry):
    kf, belief0, z = _system()
    nan_prior = GaussianBelief(belief0.mean.clone(), belief0.cov)
    nan_prior.mean[1, 0] = float("nan")
    with pytest.raises(ValueError, match="belief0.mean: contains NaN"):  # was: NaN output, silently
        entry(kf, nan_prior, z)
    negative = GaussianBelief(belief0.mean, -belief0.cov)
    # was: LinAlgError
    with pytest.raises(ValueError, match="belief0.cov: covariance is not positive semi-definite"):
        entry(kf, negative, z)
    # was: batch (2, 3)
    with pytest.raises(ValueError, match=r"z: batch shape \(8, 2, 3\) does not broadcast"):
        entry(kf, belief0, z.unsqueeze(1).expand(8, 2, 3, 1))
    with pytest.raises(TypeError, match="z: expected a tensor"):
        entry(kf, belief0, z.tolist())
    with pytest.raises(ValueError, match=r"z: expected shape \(T, \*B, 1\)"):
        entry(kf, belief0, z[..., 0])  # a scalar sensor's data without their event axis
    with pytest.raises(TypeError, match="belief0: dtype torch.float32 differs from the filter's"):
        entry(kf, belief0.to(torch.float32), z)
    with pytest.raises(TypeError, match="belief0: expected a GaussianBelief"):
        entry(kf, belief0.mean, z)
    with pytest.raises(ValueError, match="belief0: state dimension 3"):
        entry(kf, GaussianBelief(torch.zeros(3, 3, dtype=D), torch.eye(3, dtype=D)), z)


def test_parallel_filter_accepts_what_run_filter_accepts():
    kf, belief0, z = _system()
    want = run_filter(kf, belief0, z)
    for got in (parallel.filter(kf, belief0, z.float()),  # another floating dtype: cast to the belief's
                parallel.filter(kf, belief0, z[:, :1].expand(8, 3, 1).contiguous())):
        assert got.belief.mean.dtype == D and got.belief.batch_shape == (8, 3)
    torch.testing.assert_close(parallel.filter(kf, belief0, z).belief.mean, want.belief.mean,
                               rtol=1e-9, atol=1e-9)
    shared = parallel.filter(kf, belief0, z[:, :1])  # one measurement shared by every run broadcasts
    assert shared.belief.batch_shape == (8, 3)


def test_associative_scan_checks_its_arguments():
    x = torch.randn(5, 2)
    with pytest.raises(TypeError, match="op: expected a callable"):
        associative_scan(None, (x,))
    with pytest.raises(TypeError, match="elems: expected a non-empty tuple of tensors"):
        associative_scan(lambda a, b: a, x)
    with pytest.raises(TypeError, match="elems: expected a non-empty tuple"):
        associative_scan(lambda a, b: a, ())
    with pytest.raises(ValueError, match="elems: expected tensors sharing a leading"):
        associative_scan(lambda a, b: a, (x, torch.randn(4, 2)))


# -- torchmm.fusion ----------------------------------------------------------------------------------

def _tracks():
    a = GaussianBelief(torch.tensor([0.0, 1.0], dtype=D), torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=D))
    b = GaussianBelief(torch.tensor([1.0, 0.0], dtype=D), torch.tensor([[1.0, 0.2], [0.2, 3.0]], dtype=D))
    return a, b


def test_fuse_tracks_refuses_an_indefinite_track():
    """An indefinite track covariance gave a fused covariance of exactly 0 and a mean outside both tracks."""
    a, _ = _tracks()
    bad = GaussianBelief(torch.tensor([1.0, 0.0], dtype=D), torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=D))
    with pytest.raises(ValueError, match=r"tracks\[1\].cov: covariance is not positive semi-definite"):
        fuse_tracks([a, bad])
    with pytest.raises(ValueError, match=r"tracks\[1\].cov: covariance is not positive semi-definite"):
        fuse_tracks([a, bad], method="covariance_intersection")
    # relative to the matrix's scale: a covariance of 1e-12 is held to the same standard
    tiny = GaussianBelief(bad.mean, 1e-12 * bad.cov)
    with pytest.raises(ValueError, match=r"tracks\[1\].cov: covariance is not positive semi-definite"):
        fuse_tracks([a, tiny])
    lopsided = GaussianBelief(bad.mean, 1e-12 * torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=D))
    with pytest.raises(ValueError, match=r"tracks\[1\].cov: covariance is not symmetric"):
        fuse_tracks([a, lopsided])
    # one belief
    with pytest.raises(ValueError, match=r"tracks.cov: covariance is not positive semi-definite"):
        fuse_tracks(GaussianBelief(torch.stack([a.mean, bad.mean]), torch.stack([a.cov, bad.cov])))


def test_fuse_tracks_checks_values_shapes_and_types():
    a, b = _tracks()
    nan = GaussianBelief(torch.tensor([float("nan"), 0.0], dtype=D), b.cov)
    with pytest.raises(ValueError, match=r"tracks\[1\].mean: contains NaN"):
        fuse_tracks([a, nan])
    with pytest.raises(ValueError, match=r"tracks\[1\]: state dimension 3 differs from tracks\[0\]'s 2"):
        fuse_tracks([a, GaussianBelief(torch.zeros(3, dtype=D), torch.eye(3, dtype=D))])
    with pytest.raises(TypeError, match=r"tracks\[1\]: dtype torch.float32 differs"):
        fuse_tracks([a, b.to(torch.float32)])
    with pytest.raises(ValueError, match="tracks: batch shapes"):
        fuse_tracks([a.expand(2), b.expand(3)])
    with pytest.raises(TypeError, match="tracks: expected a non-empty sequence of beliefs"):
        fuse_tracks([a, b.mean])
    with pytest.raises(TypeError, match="tracks: expected"):
        fuse_tracks(a.mean)
    with pytest.raises(ValueError, match="tracks: one belief needs a track axis"):
        fuse_tracks(a)
    with pytest.raises(ValueError, match="method: expected one of"):
        fuse_tracks([a, b], method="average")
    with pytest.raises(TypeError, match="cross_covs: expected a tensor"):
        fuse_tracks([a, b], [[0.0]])
    with pytest.raises(TypeError, match="cross_covs: dtype"):
        fuse_tracks([a, b], torch.zeros(2, 2, 2, 2, dtype=torch.float32))
    cross = torch.zeros(2, 2, 2, 2, dtype=D)
    cross[0, 1] = cross[1, 0] = 5 * torch.eye(2, dtype=D)  # |P_12| > sqrt(P_11 P_22): no joint covariance
    with pytest.raises(ValueError, match="cross_covs: covariance is not positive semi-definite"):
        fuse_tracks([a, b], cross)
    cross[0, 1] = 0.1 * torch.eye(2, dtype=D)  # P_12 != P_21^T
    cross[1, 0] = 0.0
    with pytest.raises(ValueError, match="cross_covs: covariance is not symmetric"):
        fuse_tracks([a, b], cross)


def test_fuse_tracks_still_fuses_valid_tracks():
    a, b = _tracks()
    fused = fuse_tracks([a, b])
    info = torch.linalg.inv(a.cov) + torch.linalg.inv(b.cov)
    torch.testing.assert_close(fused.cov, torch.linalg.inv(info))
    tiny = fuse_tracks([GaussianBelief(a.mean, 1e-12 * a.cov), GaussianBelief(b.mean, 1e-12 * b.cov)])
    torch.testing.assert_close(tiny.mean, fused.mean)  # the weights are scale-free
    perfect = fuse_tracks([a, GaussianBelief(b.mean, torch.zeros(2, 2, dtype=D))])  # a PSD (zero) covariance
    torch.testing.assert_close(perfect.mean, b.mean)


def test_fuse_and_fusion_weights_check_their_inputs():
    P = torch.zeros(4, 2, 2, 1, 1, dtype=D)
    P[:, 0, 0], P[:, 1, 1] = 1.0, 3.0
    mean = torch.randn(4, 5, 2, 1, dtype=D)
    assert fuse(mean, P).mean.shape == (4, 5, 1)
    bad = P.clone()
    bad[2, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="P: contains NaN"):
        fusion_weights(bad)
    with pytest.raises(ValueError, match="P: contains NaN"):
        fuse(mean, bad)
    bad = P.clone()
    bad[1, 1, 1] = -3.0
    with pytest.raises(ValueError, match="P: covariance is not positive semi-definite"):
        fusion_weights(bad)
    with pytest.raises(TypeError, match="P: expected a tensor"):
        fusion_weights(P.tolist())
    with pytest.raises(ValueError, match="method: expected one of"):
        fusion_weights(P, "average")
    with pytest.raises(ValueError, match=r"mean: expected shape \(4, \*B, 2, 1\)"):
        fuse(mean[:3], P)
    with pytest.raises(ValueError, match="mean: contains NaN"):
        fuse(torch.full_like(mean, float("nan")), P)
    with pytest.raises(ValueError, match="components: expected state indices"):
        fuse(mean, P, components=[3])
