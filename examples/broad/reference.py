"""Reference rows for the BROAD comparison from maintained packages, and the published numbers.

* :func:`vqf_9d`: VQF (Laidig and Seel, Information Fusion 2023) 9-D with its default settings,
  the online (causal) ``vqf.VQF`` class like every other row (on the 23 trials: 2.37 total, 2.22
  heading, 0.66 inclination, the figures the issue quotes); ``offline=True`` runs
  ``vqf.offlineVQF`` instead (acausal, it uses future samples: 2.03 / 1.93 / 0.51). Its earth
  frame is ENU like BROAD's reference, the quaternions are used as they come.
* :func:`vqf_6d`: the same online ``vqf.VQF`` fed the gyroscope and accelerometer only, its
  ``quat6D`` output (heading arbitrary: scored on inclination only).
* :func:`riann_6d`: RIANN (Weber, Guehmann and Seel, AI 2(3):444, 2021), the trained network
  of the ``riann`` package (ONNX, run by ``onnxruntime``) over each whole trial at its rate,
  gyroscope and accelerometer only (heading arbitrary: scored on inclination only).
* :func:`madgwick`, :func:`mahony`: the ``ahrs`` package's filters (pure Python, ~0.7 ms per
  sample). Their earth frames differ (checked on trial 01 and in their source, ahrs 0.4):
  Madgwick's magnetic reference is ``(b_x, 0, b_z)``, x north and z up, so North-West-Up and
  ``q_ENU = q_z(90 deg) * q_ahrs`` (without it the heading is off by 90 deg); Mahony's is
  ``(0, b_y, b_z)``, y north, so ENU already. They start from the first sample's TRIAD attitude
  (given as their ``q0``, in their frame), as the project's filters do.
* :func:`published`: the BROAD authors' own per-trial RMSE for Madgwick and Mahony at their
  tuned gains (``published/results_{madgwick,mahony}_average_rmse.json``).

``vqf``, ``ahrs`` and ``riann`` are optional: ``pip install 'manifold_nets[broad]'`` (``pip
install riann`` for RIANN).
Every estimator returns quaternions ``(T, 4)`` (w, x, y, z) in ENU per trial.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .data import Trial
from .filters import initial_attitude
from .metric import matrix_to_quat, quat_conj, quat_multiply

__all__ = ["vqf_9d", "vqf_6d", "riann_6d", "madgwick", "mahony", "published", "PUBLISHED_GAINS"]

#: the gains of the BROAD authors' published rows (``tagp_parameters`` of the JSON files)
PUBLISHED_GAINS = {"madgwick": {"beta": 0.12}, "mahony": {"Kp": 0.74, "Ki": 0.0012}}
_NWU_TO_ENU = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])


def _need(module: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(
            f"the BROAD reference rows need the optional package {module.split('.')[0]!r}: "
            "pip install 'manifold_nets[broad]' (or pip install vqf ahrs)."
        ) from None


def vqf_9d(trials: list[Trial], offline: bool = False) -> list[np.ndarray]:
    """VQF 9-D, default parameters (online, or the acausal offline variant): ``(T, 4)`` each."""
    vqf = _need("vqf")
    out = []
    for t in trials:
        args = [np.ascontiguousarray(a, dtype=np.float64) for a in (t.gyr, t.acc, t.mag)]
        if offline:
            res = vqf.offlineVQF(*args, 1.0 / t.rate)
        else:
            res = vqf.VQF(1.0 / t.rate).updateBatch(*args)
        out.append(np.asarray(res["quat9D"], dtype=np.float64))
    return out


def vqf_6d(trials: list[Trial]) -> list[np.ndarray]:
    """VQF 6-D (no magnetometer), default parameters, online: ``quat6D`` ``(T, 4)`` each."""
    vqf = _need("vqf")
    out = []
    for t in trials:
        gyr, acc = (np.ascontiguousarray(a, dtype=np.float64) for a in (t.gyr, t.acc))
        out.append(np.asarray(vqf.VQF(1.0 / t.rate).updateBatch(gyr, acc)["quat6D"], np.float64))
    return out


def riann_6d(trials: list[Trial]) -> list[np.ndarray]:
    """RIANN (``riann.RIANN().predict``, the whole trial at once, which equals its step-by-step
    use): ``(T, 4)`` unit quaternions each."""
    riann = _need("riann")
    ort = _need("onnxruntime")
    onnx = str(Path(riann.__file__).parent / "riann.onnx")  # its own default lookup fails
    net = riann.RIANN(onnx)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1  # one thread, like every row
    net.session = ort.InferenceSession(onnx, opts)
    out = []
    for t in trials:
        q = np.asarray(net.predict(t.acc, t.gyr, t.rate), dtype=np.float64)
        out.append(q / np.linalg.norm(q, axis=1, keepdims=True))
    return out


def _ahrs(cls_name: str, to_enu: np.ndarray, trials, m_ref, **gains) -> list[np.ndarray]:
    """Runs ``ahrs.filters.<cls_name>``; ``to_enu`` the quaternion from its earth frame to ENU."""
    filters = _need("ahrs.filters")
    cls = getattr(filters, cls_name)
    out = []
    for t in trials:
        q_enu = matrix_to_quat(initial_attitude(t.acc[0], t.mag[0], m_ref))
        q0 = quat_multiply(quat_conj(to_enu), q_enu)
        f = cls(gyr=t.gyr, acc=t.acc, mag=t.mag, frequency=t.rate, q0=q0, **gains)
        out.append(quat_multiply(to_enu, np.asarray(f.Q, dtype=np.float64)))
    return out


def madgwick(trials: list[Trial], m_ref: np.ndarray, gain: float = 0.12) -> list[np.ndarray]:
    """``ahrs.filters.Madgwick`` (MARG) with ``gain`` (beta; BROAD's 0.12): ENU quaternions."""
    return _ahrs("Madgwick", _NWU_TO_ENU, trials, m_ref, gain=gain)


def mahony(
    trials: list[Trial], m_ref: np.ndarray, k_P: float = 0.74, k_I: float = 0.0012
) -> list[np.ndarray]:
    """``ahrs.filters.Mahony`` (MARG) with BROAD's tuned gains by default, ENU quaternions."""
    return _ahrs("Mahony", np.array([1.0, 0, 0, 0]), trials, m_ref, k_P=k_P, k_I=k_I)


def published(results_dir: str | Path, names: list[str]) -> dict[str, dict[str, dict[str, float]]]:
    """``{method: {trial: {"total", "heading", "inclination"} deg}}`` of the authors' results.

    ``results_dir`` holds ``results_{madgwick,mahony}_average_rmse.json``; a trial missing from
    a file is left out of that method (a clear KeyError would hide the others).
    """
    out = {}
    for method in ("madgwick", "mahony"):
        path = Path(results_dir) / f"results_{method}_average_rmse.json"
        raw = json.loads(path.read_text())
        rows = {}
        for name in names:
            entry = raw.get("trials", {}).get(name, {}).get("tagp_parameters")
            if entry is not None:
                rows[name] = {k: float(entry[f"{k}_rmse_deg"]) for k in
                              ("total", "heading", "inclination")}  # fmt: skip
        out[f"{method} (published)"] = rows
    return out
