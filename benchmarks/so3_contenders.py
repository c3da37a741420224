"""The contenders of the SO(3) benchmark (``bench_so3.py``): ``groups.SO3`` (and, for
``--baseline``, this library as of a git revision), roma, PyPose, kornia and scipy, each as
``op -> function`` over the same inputs, which are made here too.

A helper of ``benchmarks/bench_so3.py`` (which imports it from beside itself), not a benchmark
of its own. ``LIBS`` and ``BASELINE`` are the run's list of libraries, extended by
``bench_so3.main`` for ``--baseline``.
"""

from __future__ import annotations

import atexit
import importlib.util
import math
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from groups import SO3  # noqa: E402

try:  # the peers are the optional `bench` extra
    import roma
except ImportError:  # pragma: no cover - reported in the results
    roma = None
try:
    import pypose as pp
except ImportError:  # pragma: no cover
    pp = None
try:
    import kornia
    import kornia.geometry.conversions as kc
except ImportError:  # pragma: no cover
    kornia = kc = None

G = SO3()
DTYPES = {"float32": torch.float32, "float64": torch.float64}
OPS = ("exp", "log", "compose")
PEERS = ("roma", "pypose (quat)", "pypose (matrix)", "kornia", "scipy")
LIBS: list[str] = ["ours", *PEERS]  # main() inserts "ours@REV" after "ours" for --baseline
BASELINE: dict[str, object] = {}  # "ours@REV" -> that revision's SO3()


def make_inputs(n: int, dtype: torch.dtype, seed: int) -> dict:
    """Rotation vectors with uniform axes and angles uniform in ``[0, pi)``, and their images.

    Everything is computed in float64 by scipy (no library under test makes its own inputs),
    then cast to ``dtype``. Two independent sets, ``a`` and ``b``, feed ``compose``.
    Returns torch tensors ``v (n, 3)``, ``R (n, 3, 3)``, ``q (n, 4)`` (scalar last, PyPose's and
    scipy's order) per set, and the numpy/scipy objects for scipy's own rows.
    """
    g = torch.Generator().manual_seed(seed)
    out: dict = {}
    for key in ("a", "b"):
        axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
        axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
        angle = torch.rand(n, 1, generator=g, dtype=torch.float64) * math.pi
        v64 = (axis * angle).numpy()
        rot = Rotation.from_rotvec(v64)
        out[key] = {
            "v": torch.from_numpy(v64).to(dtype),
            "R": torch.from_numpy(rot.as_matrix()).to(dtype),
            "q": torch.from_numpy(rot.as_quat()).to(dtype),
            "v_np": v64,
            "R_np": rot.as_matrix(),
            "rot": rot,
        }
    return out


# --------------------------------------------------------------------------- the contenders


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, capture_output=True, text=True, check=False
    ).stdout.strip()


def load_baseline(rev: str):
    """``groups.SO3()`` as of git revision ``rev``, imported under another name.

    The package's files at ``rev`` are written to a temporary folder and imported as
    ``groups_at_<rev>`` (the package uses relative imports only), so the working tree and the
    baseline run side by side in one process: a before/after column from the same run.
    """
    files = [f for f in _git("ls-tree", "--name-only", rev, "groups/").split() if f.endswith(".py")]
    if not files:
        raise SystemExit(f"--baseline {rev}: no groups/*.py at that revision (is it a git rev?)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_so3_baseline_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    (tmp / "groups").mkdir()
    for f in files:
        (tmp / "groups" / Path(f).name).write_text(_git("show", f"{rev}:{f}") + "\n")
    name = "groups_at_" + "".join(ch if ch.isalnum() else "_" for ch in rev)
    spec = importlib.util.spec_from_file_location(
        name, tmp / "groups" / "__init__.py", submodule_search_locations=[str(tmp / "groups")]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.SO3()


def torch_ops(lib: str) -> dict[str, tuple[str, Callable] | None]:
    """``op -> (input key, function of the input tensors)`` for a torch library, None if absent."""
    if lib == "ours" or lib in BASELINE:
        g = G if lib == "ours" else BASELINE[lib]
        return {
            "exp": ("v", g.exp),
            "log": ("R", g.log),
            "compose": ("R", g.compose),
        }
    if lib == "roma" and roma is not None:
        return {
            "exp": ("v", roma.rotvec_to_rotmat),
            "log": ("R", roma.rotmat_to_rotvec),
            "compose": ("R", lambda x, y: roma.rotmat_composition((x, y))),
        }
    if lib == "pypose (quat)" and pp is not None:
        return {
            "exp": ("v", lambda v: pp.so3(v).Exp()),
            "log": ("q", lambda q: pp.SO3(q).Log()),
            "compose": ("q", lambda p, q: pp.SO3(p) @ pp.SO3(q)),
        }
    if lib == "pypose (matrix)" and pp is not None:
        return {
            "exp": ("v", lambda v: pp.so3(v).Exp().matrix()),
            "log": ("R", lambda r: pp.mat2SO3(r, check=False).Log()),
            "compose": None,
        }
    if lib == "kornia" and kc is not None:
        return {
            "exp": ("v", kc.axis_angle_to_rotation_matrix),
            "log": ("R", kc.rotation_matrix_to_axis_angle),
            "compose": None,
        }
    return {op: None for op in OPS}


def scipy_op(op: str, a: dict, b: dict) -> Callable:
    """scipy's Rotation on numpy float64 (quaternions inside; compose multiplies quaternions)."""
    if op == "exp":
        return lambda: Rotation.from_rotvec(a["v_np"]).as_matrix()
    if op == "log":
        return lambda: Rotation.from_matrix(a["R_np"]).as_rotvec()
    return lambda: a["rot"] * b["rot"]


def closure(lib: str, op: str, inputs: dict, backward: bool) -> Callable | None:
    """A no-argument callable that runs one forward (and backward) pass, or None if n/a."""
    if lib == "scipy":
        dtype_ok = inputs["a"]["v"].dtype == torch.float64
        return scipy_op(op, inputs["a"], inputs["b"]) if dtype_ok and not backward else None
    entry = torch_ops(lib)[op]
    if entry is None:
        return None
    key, fn = entry
    args = [inputs["a"][key]] if op != "compose" else [inputs["a"][key], inputs["b"][key]]
    if not backward:
        return lambda: fn(*args)
    leaves = [x.clone().requires_grad_(True) for x in args]
    out = fn(*leaves)
    upstream = torch.randn(out.shape, dtype=out.dtype, generator=torch.Generator().manual_seed(1))
    return lambda: torch.autograd.grad(fn(*leaves), leaves, upstream)

