"""Compiled step data of the fast path: one CasADi-generated C function, built once and cached.

:meth:`planning.mpc_qp.MpcQp.data` turns the raw inputs of one control step (measured state,
goal, the linearization point's inputs, the field's distance and gradient at its knots, the
speed and acceleration cut directions, the bounds) into the rolled-out linearization point,
``theta`` and the scaled OSQP data ``q, l, u, A_x`` plus the scaled warm start. All of it is
affine or a fixed rollout, so it is written once as a CasADi SX expression of the same affine
maps the NumPy path uses, generated to C with :class:`casadi.CodeGenerator` and compiled with
``cc -O2 -shared -fPIC`` (as acados compiles its solvers once per formulation).

Cache. The shared library is stored as ``<cache>/mpc/onfly_qpdata_<hash>.so`` where the hash
covers everything that shapes the generated code: this module's format version, the CasADi
version, the compiler flags, the problem sizes, and the bytes of every affine map and scaling
(so any change of a weight, limit, horizon, cut count or acceleration mode is a new entry).
``<cache>`` is ``$ONFLY_CACHE_DIR``, else ``$XDG_CACHE_HOME/onfly``, else ``~/.cache/onfly``.
Concurrent builders (two benchmark workers) each write into their own temporary directory and
publish with an atomic ``os.replace``, so a reader never sees a partial file; both produce the
same bytes; an advisory lock file makes the second wait instead of compiling again. Every
load is checked against the NumPy path on one input before use.

The library is called through ``ctypes`` with persistent buffers (CasADi's C API:
``f(const double** arg, double** res, long long* iw, double* w, int mem)``), a few
microseconds per call. Without a compiler (``$CC``, ``gcc`` or ``cc`` on ``PATH``) or when
the build fails, :class:`CodegenError` is raised and :class:`planning.mpc_qp.MpcQp` falls back
to NumPy, which gives the same numbers to rounding (tests compare both to 1e-9).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import casadi as ca
import numpy as np
import scipy.sparse as sp

try:  # POSIX only; elsewhere concurrent builders just build twice
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

from planning.mpc_model import NU, NX

if TYPE_CHECKING:  # pragma: no cover
    from planning.mpc_qp import MpcQp

__all__ = ["CodegenError", "cache_dir", "compile_qp_data", "find_compiler", "formulation_hash", "CODEGEN_VERSION"]

logger = logging.getLogger(__name__)

#: Bump when the generated function's inputs, outputs or arithmetic change.
CODEGEN_VERSION = "qpdata-2"
_CFLAGS = ("-O2", "-shared", "-fPIC")
_INF = 1e30
_BIG = 1e20


class CodegenError(RuntimeError):
    """The compiled step data cannot be built or loaded (no compiler, build failure, bad cache)."""


def cache_dir() -> Path:
    """Where compiled formulations live: ``$ONFLY_CACHE_DIR``, ``$XDG_CACHE_HOME/onfly`` or
    ``~/.cache/onfly``, plus ``/mpc``."""
    root = os.environ.get("ONFLY_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = os.path.join(xdg, "onfly") if xdg else os.path.join(os.path.expanduser("~"), ".cache", "onfly")
    return Path(root) / "mpc"


def find_compiler() -> str | None:
    """Path of the C compiler: ``$CC`` if set (and found), else ``gcc``, else ``cc``; None if none."""
    cc = os.environ.get("CC")
    if cc:
        return shutil.which(cc)
    return shutil.which("gcc") or shutil.which("cc")


def _maps(qp: "MpcQp") -> list[tuple[str, object]]:
    return [
        ("sq0", qp._sq0), ("sMq", qp._sMq), ("sl0", qp._sl0), ("sMl", qp._sMl), ("su0", qp._su0),
        ("sMu", qp._sMu), ("sA0", qp._sA0), ("sMA", qp._sMA), ("D", qp._D),
    ]


def formulation_hash(qp: "MpcQp") -> str:
    """SHA-256 (hex) of everything that shapes the generated code (see the module docstring)."""
    h = hashlib.sha256()
    L = qp.layout
    h.update(f"{CODEGEN_VERSION}|casadi {ca.__version__}|{' '.join(_CFLAGS)}|".encode())
    h.update(f"N={L.N} K={L.speed_cuts} Ka={L.accel_cuts} n={qp.n} m={qp.m} dt={qp._dt!r}|".encode())
    for name, arr in _maps(qp):
        h.update(name.encode())
        if sp.issparse(arr):
            m = sp.csr_matrix(arr)
            m.sort_indices()
            for part in (m.indptr, m.indices, m.data):
                h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(np.ascontiguousarray(arr, dtype=float).tobytes())
    return h.hexdigest()


def _to_dm(M) -> ca.DM:
    csc = sp.csc_matrix(M)
    csc.eliminate_zeros()
    csc.sort_indices()
    spars = ca.Sparsity(csc.shape[0], csc.shape[1], csc.indptr.tolist(), csc.indices.tolist())
    return ca.DM(spars, csc.data.tolist())


def _clip_inf(x: ca.SX) -> ca.SX:
    x = ca.if_else(x <= -_BIG, -_INF, x)
    return ca.if_else(x >= _BIG, _INF, x)


def build_function(qp: "MpcQp", name: str) -> ca.Function:
    """The SX function ``name(w (n_w,)) -> out (n_out,)`` of :class:`planning.mpc_qp.DataLayout`."""
    DL, L = qp.data_layout, qp.layout
    W = DL.w
    N, K, Ka = L.N, L.speed_cuts, L.accel_cuts
    dt = qp._dt
    w = ca.SX.sym("w", DL.n_w)

    def part(key: str) -> ca.SX:
        s = W[key]
        return w[s.start : s.stop]

    x0 = part("x0")
    U = ca.reshape(part("u_bar"), NU, N)  # column k = input k (row-major (N, 4) in w)
    G = ca.reshape(part("lin_grad"), 3, N)
    d = part("lin_d")
    # exact rollout of the linearization point (same map as planning.mpc_model.simulate)
    p, v, yaw = x0[0:3], x0[3:6], x0[6]
    states = [ca.vertcat(p, v, yaw)]
    offsets = []
    for k in range(N):
        a, r = U[0:3, k], U[3, k]
        p = p + v * dt + (0.5 * dt * dt) * a
        v = v + a * dt
        yaw = yaw + r * dt
        states.append(ca.vertcat(p, v, yaw))
        offsets.append(d[k] - ca.dot(G[:, k], p))
    theta = ca.vertcat(
        x0, part("goal"), part("psi_ref"), part("a_prev"), part("lin_grad"), ca.vertcat(*offsets),
        part("speed_dir"), part("speed_bound"), ca.vec(U[0:3, :]),
        part("accel_dir") if Ka else ca.SX(0, 1), part("pos_lo"), part("pos_hi"),
        part("pos_active"),
    )
    if theta.numel() != L.n_theta:
        raise CodegenError(f"theta has {theta.numel()} entries, layout says {L.n_theta}")
    q = ca.DM(qp._sq0) + ca.mtimes(_to_dm(qp._sMq), theta)
    lo = _clip_inf(ca.DM(qp._sl0) + ca.mtimes(_to_dm(qp._sMl), theta))
    up = _clip_inf(ca.DM(qp._su0) + ca.mtimes(_to_dm(qp._sMu), theta))
    Ax = ca.DM(qp._sA0) + ca.mtimes(_to_dm(qp._sMA), theta)
    z_warm = ca.vertcat(*states, ca.vec(U), part("s_warm")) / ca.DM(qp._D)
    out = ca.vertcat(theta, q, lo, up, Ax, z_warm)
    if out.numel() != DL.n_out:
        raise CodegenError(f"output has {out.numel()} entries, layout says {DL.n_out}")
    return ca.Function(name, [w], [ca.densify(out)], ["w"], ["out"])


def _build(qp: "MpcQp", name: str, target: Path, compiler: str) -> None:
    """Generate and compile into a private directory, then publish ``target`` atomically."""
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".build-{name}-", dir=target.parent))
    try:
        fn = build_function(qp, name)
        cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        cg.add(fn)
        cg.generate(str(tmp) + os.sep)
        so = tmp / f"{name}.so"
        cmd = [compiler, *_CFLAGS, "-o", str(so), str(tmp / f"{name}.c"), "-lm"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        if proc.returncode != 0:
            raise CodegenError(f"{' '.join(cmd)} failed: {proc.stderr.strip()[:500]}")
        os.replace(so, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class _CompiledData:
    """A loaded step-data library: ``obj(w, out) -> out`` with persistent ctypes buffers."""

    def __init__(self, path: Path, name: str, n_w: int, n_out: int) -> None:
        self.path = path
        lib = ctypes.CDLL(str(path))
        fn = getattr(lib, name)
        work = getattr(lib, f"{name}_work")
        ll = ctypes.c_longlong
        sz = [ll(0) for _ in range(4)]
        work.argtypes = [ctypes.POINTER(ll)] * 4
        work.restype = ctypes.c_int
        if work(*(ctypes.byref(s) for s in sz)) != 0:
            raise CodegenError(f"{path}: work-size query failed")
        n_arg, n_res, n_iw, n_wk = (max(int(s.value), 1) for s in sz)
        dp = ctypes.POINTER(ctypes.c_double)
        self._w = np.zeros(n_w)
        self._iw = np.zeros(n_iw, dtype=np.int64)
        self._work = np.zeros(n_wk)
        self._arg = (dp * n_arg)()
        self._res = (dp * n_res)()
        self._arg[0] = self._w.ctypes.data_as(dp)
        self._n_out = n_out
        self._out: np.ndarray | None = None
        fn.argtypes = [ctypes.POINTER(dp), ctypes.POINTER(dp), ctypes.POINTER(ll), dp, ctypes.c_int]
        fn.restype = ctypes.c_int
        self._fn = fn
        self._args = (self._arg, self._res, self._iw.ctypes.data_as(ctypes.POINTER(ll)), self._work.ctypes.data_as(dp), 0)
        self._lib = lib

    def __call__(self, w: np.ndarray, out: np.ndarray) -> np.ndarray:
        if out is not self._out:
            if out.shape != (self._n_out,) or out.dtype != np.float64 or not out.flags.c_contiguous:
                raise ValueError(f"out must be a contiguous float64 array of shape ({self._n_out},)")
            self._res[0] = out.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
            self._out = out
        self._w[:] = w
        if self._fn(*self._args) != 0:
            raise RuntimeError(f"{self.path}: the compiled step data returned an error")
        return out


def _self_check(qp: "MpcQp", data: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> float:
    """Largest relative difference of compiled vs NumPy step data on one seeded input."""
    DL, L = qp.data_layout, qp.layout
    rng = np.random.default_rng(12345)
    w = rng.normal(size=DL.n_w)
    for key in ("lin_grad", "speed_dir", "accel_dir"):
        s = DL.w[key]
        if s.stop > s.start:
            v = w[s].reshape(-1, 3)
            w[s] = (v / np.linalg.norm(v, axis=1, keepdims=True)).ravel()
    w[DL.w["pos_lo"]] = -np.inf
    w[DL.w["pos_hi"]] = [1.0, np.inf, 2.0]
    w[DL.w["pos_active"]] = 1.0
    a = data(w, np.empty(DL.n_out)).copy()
    b = qp.data_python(w)
    return max_rel_diff(a, b)


def max_rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    """``max |a - b| / max(1, |b|)``, equal entries (infinities included) counting 0, NaN as inf."""
    same = a == b
    with np.errstate(invalid="ignore"):
        diff = np.where(same, 0.0, np.abs(a - b) / np.maximum(1.0, np.abs(b)))
    diff[np.isnan(diff)] = np.inf
    return float(diff.max(initial=0.0))


def compile_qp_data(qp: "MpcQp") -> _CompiledData:
    """Load the compiled step data of ``qp`` from the cache, building it once if missing.

    A cache entry that cannot be loaded or disagrees with the NumPy path (a corrupt file) is
    removed and rebuilt once. Raises :class:`CodegenError` when no compiler is available, the
    build fails, or the rebuilt library still disagrees.
    """
    digest = formulation_hash(qp)
    name = f"onfly_qpdata_{digest[:16]}"
    target = cache_dir() / f"{name}.so"
    DL = qp.data_layout
    last_error = ""
    for attempt in range(2):
        if not target.exists():
            compiler = find_compiler()
            if compiler is None:
                raise CodegenError("no C compiler found ($CC, gcc or cc); run scripts/setup.sh to install gcc")
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                # an advisory lock: a second process waits for the first build instead of
                # repeating it (correctness does not depend on it: publishing is atomic)
                with open(target.parent / f".{name}.lock", "a") as lock:
                    if fcntl is not None:
                        fcntl.flock(lock, fcntl.LOCK_EX)
                    if not target.exists():
                        logger.info("compiling the MPC step data once into %s", target)
                        _build(qp, name, target, compiler)
            except (OSError, subprocess.SubprocessError) as exc:
                raise CodegenError(f"cannot build {target}: {exc}") from exc
        try:
            compiled = _CompiledData(target, name, DL.n_w, DL.n_out)
            err = _self_check(qp, compiled)
            if err <= 1e-9:
                return compiled
            last_error = f"{target} disagrees with the NumPy step data (max rel diff {err:.3g})"
        except (OSError, AttributeError, CodegenError) as exc:
            last_error = f"cannot load {target}: {exc}"
        logger.warning("%s; removing it%s", last_error, " and rebuilding" if attempt == 0 else "")
        try:
            target.unlink()
        except OSError:
            pass
    raise CodegenError(last_error)
