"""Compiled step data: the same QP data as NumPy, cached by formulation, safe to build twice."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from planning import mpc_codegen
from planning.mpc_codegen import CodegenError, cache_dir, formulation_hash, max_rel_diff
from planning.mpc_model import MpcFormulation
from planning.mpc_qp import MpcQp
from planning.planner_config import PlannerConfig

SMALL = PlannerConfig(horizon_steps=8)
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture()
def cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("ONFLY_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def seeded_inputs(qp: MpcQp, seed: int, volume: bool) -> np.ndarray:
    """Step inputs of a plausible state: unit gradients and cut directions, bounds >= v_max."""
    rng = np.random.default_rng(seed)
    DL, L = qp.data_layout, qp.layout
    W = DL.w
    w = np.zeros(DL.n_w)
    N = L.N
    w[W["x0"]] = np.concatenate([np.zeros(3), rng.normal(size=3) * 0.4, [rng.uniform(-3, 3)]])
    w[W["goal"]] = rng.normal(size=3) * 4
    w[W["psi_ref"]] = rng.uniform(-3, 3)
    w[W["a_prev"]] = rng.normal(size=3) * 0.3
    w[W["u_bar"]] = (rng.normal(size=(N, 4)) * 0.3).ravel()
    w[W["lin_d"]] = rng.uniform(0.2, 3.0, size=N)

    def unit(shape):
        v = rng.normal(size=shape)
        return (v / np.linalg.norm(v, axis=-1, keepdims=True)).ravel()

    w[W["lin_grad"]] = unit((N, 3))
    w[W["speed_dir"]] = unit((N, L.speed_cuts, 3))
    if L.accel_cuts:
        w[W["accel_dir"]] = unit((N, L.accel_cuts, 3))
    w[W["speed_bound"]] = np.maximum(0.6, rng.uniform(0.0, 1.0, size=N))
    w[W["pos_lo"]] = -rng.uniform(0.5, 5, size=3) if volume else -np.inf
    w[W["pos_hi"]] = rng.uniform(0.5, 5, size=3) if volume else np.inf
    w[W["pos_active"]] = 1.0 if volume else 0.0
    w[W["s_warm"]] = rng.uniform(0, 0.1, size=N)
    return w


@pytest.mark.parametrize("mode", ["norm", "per_axis"])
def test_compiled_and_python_step_data_agree_to_1e9(cache, mode):
    qp = MpcQp(MpcFormulation(dataclasses.replace(SMALL, accel_limit_mode=mode)), backend="compiled")
    assert qp.backend == "compiled"
    O = qp.data_layout.out
    for seed in range(10):
        w = seeded_inputs(qp, seed, volume=seed % 2 == 0)
        compiled = qp.data(w, backend="compiled").copy()
        python = qp.data(w, backend="python").copy()
        assert max_rel_diff(compiled, python) <= 1e-9
        # and the data are the QP's own maps: theta -> scaled vectors and matrix
        th = python[O["theta"]]
        q, l, u = qp._scaled_vectors(th.copy())
        np.testing.assert_array_equal(python[O["q"]], q)
        np.testing.assert_array_equal(python[O["l"]], l)
        assert np.all(np.abs(compiled[O["l"]]) <= 1e30) and np.all(np.abs(compiled[O["u"]]) <= 1e30)


def test_solutions_of_both_backends_are_the_same(cache):
    form = MpcFormulation(SMALL)
    a, b = MpcQp(form, backend="compiled"), MpcQp(form, backend="python")
    w = seeded_inputs(a, 3, volume=True)
    sa = a.solve_data(a.data(w), a.data(w)[a.data_layout.out["z_warm"]], None)
    sb = b.solve_data(b.data(w), b.data(w)[b.data_layout.out["z_warm"]], None)
    assert sa.iterations == sb.iterations
    np.testing.assert_allclose(sa.z, sb.z, atol=1e-9)


def test_no_compiler_falls_back_to_numpy_and_compiled_refuses(cache, monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc-for-onfly-tests")
    assert mpc_codegen.find_compiler() is None
    form = MpcFormulation(dataclasses.replace(SMALL, w_goal=1.25))  # a formulation not yet cached
    qp = MpcQp(form, backend="auto")
    assert qp.backend == "python"
    w = seeded_inputs(qp, 0, volume=False)
    assert np.all(np.isfinite(qp.data(w)[qp.data_layout.out["q"]]))
    with pytest.raises(CodegenError, match="no C compiler"):
        MpcQp(form, backend="compiled")
    assert not any(cache.glob("**/*.so"))


def test_cache_is_keyed_by_the_formulation_and_reused(cache):
    a = MpcQp(MpcFormulation(SMALL), backend="compiled")
    files = sorted(cache_dir().glob("*.so"))
    assert len(files) == 1 and files[0] == a._compiled.path
    stamp = files[0].stat().st_mtime_ns
    b = MpcQp(MpcFormulation(SMALL), backend="compiled")  # loaded, not rebuilt
    assert b._compiled.path == files[0] and files[0].stat().st_mtime_ns == stamp
    changed = MpcQp(MpcFormulation(dataclasses.replace(SMALL, w_jerk=3.0)), backend="python")
    assert formulation_hash(changed) != formulation_hash(a)
    solver_only = MpcQp(MpcFormulation(dataclasses.replace(SMALL, qp_eps_abs=1e-4)), backend="python")
    assert formulation_hash(solver_only) == formulation_hash(a)  # OSQP settings shape no data
    assert not list(cache_dir().glob(".build-*"))  # no temporary directory left behind


def test_corrupt_cache_entry_is_rebuilt(cache):
    a = MpcQp(MpcFormulation(SMALL), backend="compiled")
    path = a._compiled.path
    form = MpcFormulation(dataclasses.replace(SMALL, w_vel=0.2))
    name = f"onfly_qpdata_{formulation_hash(MpcQp(form, backend='python'))[:16]}.so"
    (cache_dir() / name).write_bytes(b"not a shared library")
    b = MpcQp(form, backend="compiled")
    assert b.backend == "compiled" and b._compiled.path.name == name
    assert (cache_dir() / name).stat().st_size > 1000
    assert path.exists()


def test_two_processes_building_at_once_share_one_intact_entry(cache):
    code = (
        "from planning.mpc_model import MpcFormulation; from planning.mpc_qp import MpcQp;"
        "from planning.planner_config import PlannerConfig;"
        "q = MpcQp(MpcFormulation(PlannerConfig(horizon_steps=6, w_yaw=1.5)), backend='compiled');"
        "print(q._compiled.path)"
    )
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    procs = [
        subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-500:] for o in outs]
    paths = {o[0].strip() for o in outs}
    assert len(paths) == 1
    assert len(list(cache_dir().glob("*.so"))) == 1 and not list(cache_dir().glob(".build-*"))
    # the published file loads and passes the self-check in a third process
    qp = MpcQp(MpcFormulation(PlannerConfig(horizon_steps=6, w_yaw=1.5)), backend="compiled")
    assert str(qp._compiled.path) in paths


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("ONFLY_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "onfly" / "mpc"
    monkeypatch.setenv("ONFLY_CACHE_DIR", str(tmp_path / "own"))
    assert cache_dir() == tmp_path / "own" / "mpc"
