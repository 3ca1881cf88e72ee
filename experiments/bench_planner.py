"""Benchmark of the receding-horizon planner: fast QP path against the ipopt reference.

Seeded obstacle scenes (:func:`planning.analytic_field.obstacle_scene`: walls, pillar forests,
gaps, overhangs) are flown in closed loop by the fast path (the exact double integrator driven by
each step's first command). It reports

* ``fast_ms_median`` / ``fast_ms_p90`` / ``fast_ms_p99``: wall time of one control step, i.e.
  ``Planner.step`` end to end (field queries, building the QP data, the OSQP update and solve,
  speed refinements, the rollout and safety check), over every step of every episode, with
  the compiled QP data (:mod:`planning.mpc_codegen`); ``fast_ms_p99_warm`` leaves out each
  episode's first (cold-start) step;
* ``python_ms_*``: the same step with the NumPy QP data, run in lockstep on the same states
  (the two paths give the same commands to rounding: ``python_vs_compiled_max_command_diff``);
  the order of the two calls alternates every step;
* ``osqp_ms_*``: the floor, OSQP alone on the same matrices: the wall time of the step's OSQP
  calls (in-place data update, warm start and solve, summed over its QPs), measured inside the
  compiled step; ``fast_over_osqp`` = fast median / OSQP median;
* ``max_accel_norm_mps2`` / ``max_speed_mps``: the largest commanded acceleration norm and
  speed over every closed-loop step, against ``a_max_mps2`` / ``v_max_mps``;
* ``guide_ms_max`` / ``guide_searches``: the guide search's worst wall time and how many ran;
* ``reference_ms_median``: ipopt (:class:`planning.mpc_nlp.MpcNlp`, exact speed norm, exact
  field constraints through a callback) on the *same* problems (the theta the fast step posed,
  started from the same linearization point), every ``--reference-every``-th step, same run;
  ``speedup`` = reference median / fast median;
* agreement on those problems, first command relative to its bound (``max |du_i| / u_max_i``)
  and cost relative to ``max(|J_ref|, 1)`` (the cost tends to 0 at the goal, where a relative
  difference means nothing):
  - ``max_first_control_diff`` / ``cost_rel_diff`` (max over problems): the fast path's QP
    iterated to its fixed point (``Planner.converge`` with OSQP eps 1e-6 and the speed norm
    held to 1e-4 instead of the fast path's 1 %) vs ipopt
    started at that point (the problem is nonconvex; this compares the same local optimum), i.e.
    whether the two solvers solve the same problem;
  - ``rti_first_control_diff_median`` / ``_p90`` / ``_max`` and ``rti_cost_rel_diff_max``: the
    single real-time iteration the fast path actually executes (one QP, eps 1e-3) vs the timed
    ipopt solve (started, like the fast step, from the shifted previous plan);
* ``fast_cpu_ms_*`` / ``reference_cpu_ms_median``: the same as CPU time (the step's own
  ``cpu_time_ms``, thread CPU time; process CPU time for ipopt), which on a shared, loaded
  machine excludes the time the process waited for a core; wall times are the headline
  numbers, and on a loaded machine the ratios (``fast_over_osqp``, ``python_over_fast``)
  matter more than the absolute values;
* ``min_clearance_m``: exact distance (analytic geometry) along the executed paths, sampled 8
  times per control period; ``reached`` / ``episodes``; fallbacks; OSQP iterations.

Every pool is capped at ``--threads`` (default 1) with :func:`planning.threads.limit_threads`
before anything is timed; the 1-minute load average is recorded at the start and the end.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python experiments/bench_planner.py --json out.json``
(a few minutes; ``--scenes-per-kind 1 --reference-every 40`` for a quick look).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from planning.analytic_field import SCENE_KINDS, obstacle_scene
from planning.mpc_nlp import MpcNlp
from planning.planner import Fallback, Planner, ShiftedField
from planning.planner_config import PlannerConfig
from planning.threads import limit_threads
from planning.trajectory import VehicleState


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, help="planner TOML ([planner] table); defaults otherwise")
    ap.add_argument("--scenes-per-kind", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0, help="first scene seed")
    ap.add_argument("--reference-every", type=int, default=15, help="solve the reference every k-th step")
    ap.add_argument("--threads", type=int, default=1, help="compute threads per pool (BLAS, OpenMP)")
    ap.add_argument("--json", type=Path, help="write the results here")
    return ap.parse_args()


def percentile(x, q) -> float:
    return float(np.percentile(np.asarray(x, dtype=float), q)) if len(x) else float("nan")


class OsqpTimer:
    """Accumulates the wall time of a planner's OSQP calls (``MpcQp.solve_data``)."""

    def __init__(self, planner: Planner) -> None:
        self.total_s = 0.0
        qp = planner._qp
        inner = qp.solve_data

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return inner(*a, **k)
            finally:
                self.total_s += time.perf_counter() - t0

        qp.solve_data = timed

    def take_ms(self) -> float:
        out, self.total_s = self.total_s * 1e3, 0.0
        return out


def main() -> int:
    args = parse_args()
    threads = limit_threads(args.threads)
    load_start = os.getloadavg()[0]
    cfg = PlannerConfig.from_toml(args.config) if args.config else PlannerConfig()
    fast = Planner(cfg, qp_backend="compiled")
    fast.record_problems = True
    slow = Planner(cfg, qp_backend="python")
    osqp_timer = OsqpTimer(fast)
    # the fast path's tolerances (OSQP eps 1e-3, speed norm within 1 %) tightened, to compare
    # the problem each solver solves rather than the fast path's allowed inexactness
    tight_cfg = dataclasses.replace(
        cfg, qp_eps_abs=1e-6, qp_eps_rel=1e-6, qp_max_iter=100000, speed_tolerance_rel=1e-4,
        accel_tolerance_rel=1e-4, max_speed_refinements=10,
    )
    tight = Planner(tight_cfg)
    ref = MpcNlp(fast.formulation)
    L = fast.layout
    u_max = np.array([cfg.a_max_mps2] * 3 + [cfg.yaw_rate_max_rps])
    dt = cfg.dt_s

    step_ms, warm_ms, iters, osqp_solves, step_cpu_ms, ref_cpu_ms = [], [], [], [], [], []
    py_ms, py_cpu_ms, osqp_ms, guide_ms, cmd_diff = [], [], [], [], 0.0
    max_acc, max_speed, max_acc_axis = 0.0, 0.0, 0.0
    ref_ms, du_conv, dj_conv, du_rti, dj_rti, records = [], [], [], [], [], []
    min_clear, reached, episodes, fallbacks, ref_failures = np.inf, 0, 0, 0, 0
    t_start = time.perf_counter()
    for seed in range(args.seed, args.seed + args.scenes_per_kind):
        for kind in SCENE_KINDS:
            scene = obstacle_scene(kind, seed, clearance_m=cfg.d_safe_m)
            fast.reset()
            slow.reset()
            p, v, yaw, a = scene.start.copy(), np.zeros(3), scene.start_yaw, np.zeros(3)
            path = [p.copy()]
            max_steps = int((2.0 * np.linalg.norm(scene.goal - scene.start) / cfg.v_max_mps + 15.0) / dt)
            done = False
            for k in range(max_steps):
                state = VehicleState(k * dt, p, v, yaw, 0.0, a)
                if k % 2:
                    res_py = slow.step(state, scene.goal, scene.field)
                    osqp_timer.take_ms()
                    res = fast.step(state, scene.goal, scene.field)
                else:
                    osqp_timer.take_ms()
                    res = fast.step(state, scene.goal, scene.field)
                    res_py = slow.step(state, scene.goal, scene.field)
                osqp_ms.append(osqp_timer.take_ms())
                py_ms.append(res_py.solve_time_ms)
                py_cpu_ms.append(res_py.cpu_time_ms)
                cmd_diff = max(cmd_diff, float(np.max(np.abs(res_py.command.a - res.command.a))))
                if res.guide_status:
                    guide_ms.append(res.guide_search_ms)
                step_cpu_ms.append(res.cpu_time_ms)
                step_ms.append(res.solve_time_ms)
                max_acc = max(max_acc, float(np.linalg.norm(res.command.a)))
                max_acc_axis = max(max_acc_axis, float(np.max(np.abs(res.command.a))))
                if k > 0:
                    warm_ms.append(res.solve_time_ms)
                iters.append(res.iterations)
                osqp_solves.append(res.qp_solves)
                fallbacks += res.fallback is not Fallback.NONE
                if k % args.reference_every == args.reference_every // 2:
                    prob = fast.last_problem
                    shifted = ShiftedField(scene.field, prob.origin)
                    cpu0 = time.process_time()
                    sol = ref.solve(prob.theta, shifted, prob.z_init)
                    ref_cpu = (time.process_time() - cpu0) * 1e3
                    if not sol.converged:
                        ref_failures += 1
                    else:
                        ref_ms.append(sol.solve_time_s * 1e3)
                        ref_cpu_ms.append(ref_cpu)
                        z_conv, _ = tight.converge(prob, scene.field, max_iterations=30, tol=1e-6)
                        # the problem is nonconvex: compare the converged QP with the reference's
                        # local optimum next to it (an untimed second solve started there)
                        sol_near = ref.solve(prob.theta, shifted, z_conv)
                        pairs = ((z_conv, sol_near, du_conv, dj_conv), (prob.z_plan, sol, du_rti, dj_rti))
                        for z, r, du_list, dj_list in pairs:
                            du_list.append(float(np.max(np.abs(z[L.idx_u[0]] - r.z[L.idx_u[0]]) / u_max)))
                            J = fast.formulation.evaluate_cost(z, prob.theta)
                            dj_list.append(abs(J - r.cost) / max(abs(r.cost), 1.0))
                        records.append(
                            {"kind": kind, "seed": seed, "step": k, "du_converged": du_conv[-1],
                             "dj_converged": dj_conv[-1], "du_rti": du_rti[-1], "dj_rti": dj_rti[-1],
                             "reference_ms": ref_ms[-1], "reference_iterations": sol.iterations}
                        )
                a = res.command.a
                p = p + v * dt + 0.5 * a * dt * dt
                v = v + a * dt
                max_speed = max(max_speed, float(np.linalg.norm(v)))
                yaw = yaw + res.command.yaw_rate * dt
                path.append(p.copy())
                if np.linalg.norm(p - res.goal_used) < 0.15 and np.linalg.norm(v) < 0.05:
                    done = True
                    break
            episodes += 1
            reached += done
            P = np.array(path)
            h = np.linspace(0.0, 1.0, 9)[:, None, None]
            dense = (P[:-1][None] * (1 - h) + P[1:][None] * h).reshape(-1, 3)
            min_clear = min(min_clear, float(scene.field.distance(dense).min()))
    wall_s = time.perf_counter() - t_start

    fast_med = float(np.median(step_ms))
    ref_med = float(np.median(ref_ms)) if ref_ms else float("nan")
    py_med = float(np.median(py_ms))
    osqp_med = float(np.median(osqp_ms))
    out = {
        "qp_backend_fast": fast.qp_backend,
        "qp_backend_python": slow.qp_backend,
        "threads": threads,
        "horizon_steps": cfg.horizon_steps,
        "dt_s": cfg.dt_s,
        "episodes": episodes,
        "reached": reached,
        "steps": len(step_ms),
        "fast_ms_median": fast_med,
        "fast_ms_p90": percentile(step_ms, 90),
        "fast_ms_p99": percentile(step_ms, 99),
        "fast_ms_p99_warm": percentile(warm_ms, 99),
        "fast_ms_max": float(np.max(step_ms)),
        "python_ms_median": py_med,
        "python_ms_p99": percentile(py_ms, 99),
        "python_cpu_ms_median": float(np.median(py_cpu_ms)),
        "python_cpu_ms_p99": percentile(py_cpu_ms, 99),
        "python_over_fast": py_med / fast_med,
        "python_vs_compiled_max_command_diff": cmd_diff,
        "osqp_ms_median": osqp_med,
        "osqp_ms_p99": percentile(osqp_ms, 99),
        "fast_over_osqp": fast_med / osqp_med,
        "max_accel_norm_mps2": max_acc,
        "max_accel_axis_mps2": max_acc_axis,
        "a_max_mps2": cfg.a_max_mps2,
        "accel_limit_mode": cfg.accel_limit_mode,
        "max_speed_mps": max_speed,
        "v_max_mps": cfg.v_max_mps,
        "guide_searches": len(guide_ms),
        "guide_ms_max": float(np.max(guide_ms)) if guide_ms else 0.0,
        "guide_ms_median": float(np.median(guide_ms)) if guide_ms else 0.0,
        "fast_cpu_ms_median": float(np.median(step_cpu_ms)),
        "fast_cpu_ms_p99": percentile(step_cpu_ms, 99),
        "reference_cpu_ms_median": float(np.median(ref_cpu_ms)) if ref_cpu_ms else float("nan"),
        "qp_iterations_median": float(np.median(iters)),
        "qp_iterations_p99": percentile(iters, 99),
        "qp_solves_per_step_mean": float(np.mean(osqp_solves)),
        "fallback_steps": int(fallbacks),
        "reference_problems": len(ref_ms),
        "reference_failures": ref_failures,
        "reference_ms_median": ref_med,
        "speedup": ref_med / fast_med,
        "max_first_control_diff": float(np.max(du_conv)) if du_conv else float("nan"),
        "first_control_diff_median": float(np.median(du_conv)) if du_conv else float("nan"),
        "first_control_diff_p90": percentile(du_conv, 90),
        "cost_rel_diff": float(np.max(dj_conv)) if dj_conv else float("nan"),
        "rti_first_control_diff_median": float(np.median(du_rti)) if du_rti else float("nan"),
        "rti_first_control_diff_p90": percentile(du_rti, 90),
        "rti_first_control_diff_max": float(np.max(du_rti)) if du_rti else float("nan"),
        "rti_cost_rel_diff_max": float(np.max(dj_rti)) if dj_rti else float("nan"),
        "min_clearance_m": min_clear,
        "d_safe_m": cfg.d_safe_m,
        "wall_time_s": wall_s,
        "load_average_1min": os.getloadavg()[0],
        "load_average_1min_start": load_start,
        "cpu_count": os.cpu_count(),
        "machine": platform.platform(),
        "config": cfg.to_dict(),
        "problems": records,
    }
    rows = [
        ("horizon steps (N)", f"{cfg.horizon_steps} x {cfg.dt_s} s"),
        ("episodes reached", f"{reached}/{episodes}"),
        ("fast step median", f"{fast_med:.3f} ms"),
        ("fast step p90 / p99", f"{out['fast_ms_p90']:.3f} / {out['fast_ms_p99']:.3f} ms"),
        ("fast step p99 (warm steps)", f"{out['fast_ms_p99_warm']:.3f} ms"),
        ("fast step CPU time median / p99", f"{out['fast_cpu_ms_median']:.3f} / {out['fast_cpu_ms_p99']:.3f} ms"),
        ("Python-data step median / p99", f"{py_med:.3f} / {out['python_ms_p99']:.3f} ms "
         f"(CPU {out['python_cpu_ms_median']:.3f} / {out['python_cpu_ms_p99']:.3f}); {out['python_over_fast']:.2f}x fast"),
        ("compiled vs Python commands", f"max |da| {cmd_diff:.2e} m/s^2"),
        ("OSQP alone (floor) median / p99", f"{osqp_med:.3f} / {out['osqp_ms_p99']:.3f} ms; fast = {out['fast_over_osqp']:.2f}x"),
        ("max commanded |a| (norm / axis)", f"{max_acc:.4f} / {max_acc_axis:.4f} m/s^2 (a_max {cfg.a_max_mps2}, {cfg.accel_limit_mode})"),
        ("max speed", f"{max_speed:.4f} m/s (v_max {cfg.v_max_mps})"),
        ("guide search worst / median", f"{out['guide_ms_max']:.1f} / {out['guide_ms_median']:.1f} ms over {len(guide_ms)} searches"),
        ("reference CPU time median", f"{out['reference_cpu_ms_median']:.1f} ms"),
        ("OSQP iterations median / p99", f"{out['qp_iterations_median']:.0f} / {out['qp_iterations_p99']:.0f}"),
        ("fallback steps", f"{fallbacks} of {len(step_ms)}"),
        ("reference (ipopt) median", f"{ref_med:.1f} ms over {len(ref_ms)} problems"),
        ("speedup", f"{out['speedup']:.0f}x"),
        ("first-control diff, converged QP", f"median {out['first_control_diff_median']:.4f}, "
         f"p90 {out['first_control_diff_p90']:.4f}, max {out['max_first_control_diff']:.4f} of bound"),
        ("cost diff, converged QP", f"{out['cost_rel_diff']:.4f} (max)"),
        ("first-control diff, one RTI", f"median {out['rti_first_control_diff_median']:.4f}, "
         f"p90 {out['rti_first_control_diff_p90']:.4f}, max {out['rti_first_control_diff_max']:.4f}"),
        ("min clearance (exact)", f"{min_clear:.3f} m (d_safe {cfg.d_safe_m} m)"),
        ("load average (1 min), start / end", f"{load_start:.2f} / {out['load_average_1min']:.2f} on {os.cpu_count()} CPUs"),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"{'metric':<{width}}  value")
    print("-" * (width + 40))
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
