"""The classical filters, the reference rows and the comparison on the BROAD test excerpt.

Runs without /work/shared: the excerpt (tests/fixtures/broad, CC-BY-4.0, see ATTRIBUTION.md) and
a magnetic reference estimated from it. Short slices keep the pure-Python filters fast.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from manifold_nets.ekf import ErrorStateEKF
from manifold_nets_examples.broad import filters as F
from manifold_nets_examples.broad.compare import comparison, markdown_table, write_results
from manifold_nets_examples.broad.data import read_trial
from manifold_nets_examples.broad.metric import rmse

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"


def _trial(n=None):
    t = read_trial(FIXTURE)
    if n is not None:
        for f in ("gyr", "acc", "mag", "quat", "movement"):
            setattr(t, f, getattr(t, f)[:n])
    return t


@pytest.fixture(scope="module")
def m_ref():
    return F.magnetic_reference([_trial()])


def test_magnetic_reference_points_north_and_down(m_ref):
    assert np.linalg.norm(m_ref) == pytest.approx(1.0)
    assert abs(m_ref[0]) < 0.1 and m_ref[1] > 0.2 and m_ref[2] < -0.8  # Berlin: dip ~68 deg


def test_complementary_beats_dead_reckoning_and_tunes(m_ref):
    t = _trial()
    dr = rmse(F.dead_reckoning([t], m_ref)[0], t.quat, t.movement)["total"]
    q = F.complementary([t], m_ref, k_p=1.0, k_i=0.0, k_m=1.0)
    assert q[0].shape == (len(t), 4)
    assert np.allclose(np.linalg.norm(q[0], axis=1), 1.0)
    assert rmse(q[0], t.quat, t.movement)["total"] < 0.8 * dr
    short = _trial(400)
    best, table = F.tune("complementary", [short], m_ref, {"k_p": [0.0, 1.0], "k_i": [0.0],
                                                           "k_m": [1.0]})  # fmt: skip
    assert len(table) == 2 and best["k_p"] == 1.0


def test_ekf_beats_dead_reckoning(m_ref):
    t = _trial(300)
    dr = rmse(F.dead_reckoning([t], m_ref)[0], t.quat, t.movement)["total"]
    q = F.ekf([t], m_ref)[0]
    assert q.shape == (300, 4) and F.ekf.seconds > 0
    assert rmse(q, t.quat, t.movement)["total"] < dr


def test_ekf_tune_runs_a_batched_grid(m_ref):
    t = _trial(60)
    best, table = F.tune("ekf", [t, t], m_ref, {"gyro": [0.01], "bias_walk": [1e-5],
                                                "acc": [0.1, 1.0], "mag": [1.0]})  # fmt: skip
    assert len(table) == 2 and best in [g for g, _ in table]


def test_analytic_jacobians_match_autograd(m_ref):
    gen = torch.Generator().manual_seed(0)
    model = F.BroadFilterModel(285.7, m_ref, gyro=torch.tensor([0.01, 0.02]), acc=0.3)
    g = model.group
    x = g.random((2,), generator=gen, dtype=torch.float64)
    x = torch.cat((x[:, :9], 0.01 * torch.randn(2, 3, generator=gen, dtype=torch.float64)), -1)
    y = torch.randn(2, 6, generator=gen, dtype=torch.float64)
    u = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    auto = ErrorStateEKF(model, progress=False)
    for a, b in zip(auto.process_jacobians(x, y, u), model.process_jacobians(x, y, u)):
        assert torch.allclose(a, b, atol=1e-9)
    w = model.drive(x, y, u)
    z = model.measure(x, w)
    for a, b in zip(auto.measurement_jacobians(x, w, z, 6), model.measurement_jacobians(x, w)):
        assert torch.allclose(a, b, atol=1e-9)
    delta = 0.1 * torch.randn(2, 6, generator=gen, dtype=torch.float64)
    J = auto.reset_jacobian(x, delta, g.rplus(x, delta))
    assert torch.allclose(J, model.reset_jacobian(x, delta), atol=1e-9)
    assert model.process_noise_cov(torch.float64).shape == (2, 6, 6)


def test_reference_rows_run_with_the_right_frames(m_ref):
    reference = pytest.importorskip("manifold_nets_examples.broad.reference")
    pytest.importorskip("vqf")
    pytest.importorskip("ahrs")
    t = _trial(600)
    dr = rmse(F.dead_reckoning([t], m_ref)[0], t.quat, t.movement)["total"]
    for q in (reference.vqf_9d([t])[0], reference.vqf_9d([t], offline=True)[0],
              reference.madgwick([t], m_ref)[0], reference.mahony([t], m_ref)[0]):  # fmt: skip
        assert q.shape == (600, 4)
        err = rmse(q, t.quat, t.movement)
        assert err["heading"] < 10 and err["total"] < dr  # a frame mix-up is off by 90 deg


def test_published_rows(tmp_path):
    from manifold_nets_examples.broad.reference import published

    for method in ("madgwick", "mahony"):
        entry = {"tagp_parameters": {"total_rmse_deg": 2.0, "heading_rmse_deg": 1.5,
                                     "inclination_rmse_deg": 1.0}}  # fmt: skip
        raw = {"tagp_parameters": {}, "trials": {"a": entry}}
        (tmp_path / f"results_{method}_average_rmse.json").write_text(json.dumps(raw))
    out = published(tmp_path, ["a", "b"])
    assert out["madgwick (published)"] == {"a": {"total": 2.0, "heading": 1.5,
                                                 "inclination": 1.0}}  # fmt: skip


def test_comparison_table_and_files(tmp_path, m_ref):
    t = _trial(400)
    est = {"dead reckoning": F.dead_reckoning([t], m_ref)}
    rows = comparison([t], est, {"x (published)": {t.name: {"total": 1.0, "heading": 1.0,
                                                             "inclination": 0.5}}})  # fmt: skip
    mean = [r for r in rows if r["trial"] == "mean"]
    assert [r["method"] for r in mean] == ["dead reckoning", "x (published)"]
    assert mean[0]["total"] == pytest.approx(rmse(est["dead reckoning"][0], t.quat,
                                                  t.movement)["total"])  # fmt: skip
    table = markdown_table(rows, "excerpt")
    assert "| dead reckoning |" in table and "CC-BY-4.0" in table
    learned = {"learned": {t.name: est["dead reckoning"][0]}}  # the lead's hook
    metrics = write_results(tmp_path, {"test": [t.name]}, {t.name: t},
                            {"dr": {t.name: est["dead reckoning"][0]}}, extra=learned)
    assert {r["method"] for r in metrics["test"]} == {"dr", "learned"}
    assert (tmp_path / "table.md").is_file() and (tmp_path / "metrics.json").is_file()
    assert (tmp_path / "figures" / f"{t.name}.png").stat().st_size > 1000
