"""``benchmarks/calibration_horizon.py`` at a tiny size: one ANEES per span of steps and factor,
each the mean over its span of the per-step ANEES that the calibration module computes, and bad
spans refused."""

from __future__ import annotations

import json

import pytest
import torch


@pytest.fixture(scope="module")
def horizon(load_script):
    return load_script("benchmarks/calibration_horizon.py")


def test_each_span_s_anees_is_the_mean_of_its_steps(horizon, tmp_path):
    from manifold_nets.calibration import nees, tangent_errors
    from manifold_nets_examples.rigid_body.calibration import _sim
    from manifold_nets_examples.rigid_body.level_scale import zoo_readout

    horizon.main(["--sequences", "2", "--length", "40", "--spans", "10", "25", "41",
                  "--sigmas", "0.3", "--write", str(tmp_path / "h")])
    result = json.loads((tmp_path / "h.json").read_text())
    assert result["spans"] == ["10-24", "25-40"]
    got = result["cases"]["nominal"]["0.3"]
    cal, system = zoo_readout("nominal")
    data = _sim(system, 2, 40, 0.3, 7)
    with torch.no_grad():
        est, cov = cal.eval()(data.measurements)
    xi = tangent_errors(system.group, est, data.states)
    s = system.group.tangent_slice("p")
    q = (nees(xi[..., s], cov[..., s, s].double()) / 3).mean(0)
    assert got["p"] == pytest.approx([float(q[10:25].mean()), float(q[25:41].mean())], rel=1e-12)
    assert "| nominal | 0.3 |" in (tmp_path / "h.md").read_text()


@pytest.mark.parametrize("spans", [["5", "20"], ["20", "10"], ["10"]])
def test_bad_spans_are_refused(horizon, spans):
    with pytest.raises(SystemExit, match="--spans"):
        horizon.main(["--spans", *spans])
