"""Scaling a covariance so that held-out errors fall inside its 3-sigma ellipsoid at the
Gaussian share (:func:`manifold_nets.calibration.conformal_scale`,
:func:`manifold_nets.covariance_training.scale_to_share`): exact on the held-out set, the share
on fresh errors of the same law whatever that law, and every refusal."""

from __future__ import annotations

import pytest
import torch
from scipy.stats import chi2

from groups import SO3, Euclidean, Product
from manifold_nets.calibration import conformal_scale, gaussian_share
from manifold_nets.covariance_training import Sequences, scale_to_share, step_nees
from manifold_nets.observer import CovarianceReadout

GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))
SHARE = gaussian_share(3, 3)  # 97.1 %


def _student(n, dof, gen):
    """3-D errors with Student-t tails (dof 3: far heavier than a Gaussian's)."""
    z = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    w = torch.distributions.Chi2(torch.tensor(float(dof), dtype=torch.float64)).sample((n, 1))
    return z / (w / dof).sqrt()


@pytest.mark.parametrize("dim", [1, 3, 6])
def test_chi_square_nees_of_a_calibrated_covariance_need_no_scale(dim):
    q = torch.as_tensor(chi2.rvs(dim, size=200_000, random_state=dim), dtype=torch.float64)
    assert conformal_scale(q, dim) == pytest.approx(1.0, abs=0.02)


def test_the_share_holds_on_fresh_errors_of_a_heavy_tailed_law():
    gen = torch.Generator().manual_seed(0)
    calib, fresh = _student(20_000, 3, gen), _student(200_000, 3, gen)
    q = calib.square().sum(-1)  # NEES of P = I
    assert float((q <= 9).double().mean()) < 0.93  # P = I is far too confident here
    s = conformal_scale(q, 3)
    assert float((q / s <= 9).double().mean()) >= SHARE  # at least the share on its own set
    share = float((fresh.square().sum(-1) / s <= 9).double().mean())
    assert share == pytest.approx(SHARE, abs=0.003)
    # the 1-sigma share is not the Gaussian one: the scale holds the share at 3 sigma only
    assert float((fresh.square().sum(-1) / s <= 1).double().mean()) > gaussian_share(1, 3) + 0.1


def test_the_scale_is_the_conformal_order_statistic():
    q = torch.arange(1.0, 101.0, dtype=torch.float64)  # k = ceil(101 * 0.9707) = 99
    assert conformal_scale(q, 3) == 99.0 / 9
    assert conformal_scale(q, 3, sigma=2.0) == 75.0 / 4  # ceil(101 * 0.7385) = 75
    assert conformal_scale(torch.tensor([4.5]), 3) == 0.5  # one value: itself


@pytest.mark.parametrize("bad, match", [
    (torch.tensor([]), "finite non-negative"),
    (torch.tensor([1.0, float("nan")]), "finite non-negative"),
    (torch.tensor([1.0, -1.0]), "finite non-negative"),
    (torch.zeros(10), "nothing to scale to"),
])
def test_bad_nees_values_are_refused(bad, match):
    with pytest.raises(ValueError, match=match):
        conformal_scale(bad, 3)


def _sequences(gen):
    errors = torch.cat([_student(6 * 40, 3, gen) * 0.1, _student(6 * 40, 3, gen) * 2.0], -1)
    known = torch.ones(6, 40, dtype=torch.bool)
    known[:, :3] = False
    return Sequences(torch.randn(6, 40, 16, generator=gen), errors.view(6, 40, 6), known)


@pytest.mark.parametrize("structure", ["diagonal", "factor", "joint"])
def test_a_readout_scaled_to_held_out_sequences_holds_the_share_there(structure):
    gen = torch.Generator().manual_seed(1)
    torch.manual_seed(0)
    r = CovarianceReadout(GROUP, 16, structure, memory=4)
    seqs = _sequences(gen)
    before = step_nees(r, seqs)
    assert set(before) == {"R", "p"} | ({"joint"} if structure == "joint" else set())
    assert all(len(q) == int(seqs.known.sum()) for q in before.values())
    scales = scale_to_share(r, seqs)
    after = step_nees(r, seqs)
    if structure == "joint":
        assert scales["R"] == scales["p"]
        assert float((after["joint"] <= 9).double().mean()) >= gaussian_share(3, 6)
    else:
        # P near I at the start: R's errors small (0.1), p's large (2)
        assert scales["R"] < 1 < scales["p"] and scales["p"] / scales["R"] > 100
        for name in ("R", "p"):
            torch.testing.assert_close(after[name], before[name] / scales[name], rtol=1e-6, atol=0)
            assert float((after[name] <= 9).double().mean()) >= SHARE
    # from NEES values of another readout (cross-fitted): the same scales as from the sequences
    other = CovarianceReadout(GROUP, 16, structure, memory=4)
    assert scale_to_share(other, before) == pytest.approx(scales)
