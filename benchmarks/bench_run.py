"""Benchmark: does the MCAP log slow the simulated trial down?

Runs the paper's velocity-step recipe (config/recipes/velocity-steps.yaml, about
650 s of simulated time, 648 k loop ticks) on the simulated rig

  1. without logging (the closed loop alone, blocks of 100 ticks),
  2. with the trial log (rig.log.TrialLogWriter: raw blocks base64 float64, the
     25 Hz channel, events, loop statistics, fsync'd flushes every second), with
     the mcap writer in its background thread (default) and in the caller's thread,
  3. the same with float32 raw arrays (recipe log.raw_dtype: float32),
  4. the whole `rig run ... --sim -q` command in a fresh process (startup included),

and prints ticks/s and the real-time factor (simulated s per wall s), best of
``--repeat`` runs, with CPU time beside wall time (the machines are shared).

    python benchmarks/bench_run.py [--repeat 3] [--recipe config/recipes/velocity-steps.yaml] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _measure(fn, repeat: int) -> dict:
    best = None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        ticks = fn()
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        if best is None or wall < best["wall_s"]:
            best = {"wall_s": wall, "cpu_s": cpu, "ticks": ticks}
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recipe", default=str(REPO / "config" / "recipes" / "velocity-steps.yaml"))
    ap.add_argument("--profile", default=str(REPO / "config" / "rigs" / "sim.yaml"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)

    from rig.commands.trial import run_sim_trial
    from rig.log import TrialLogWriter
    from rig.profile import load_profile
    from rig.recipe import load_recipe
    from rig.sim import SimRig
    from trajectories import compile_recipe

    recipe = load_recipe(args.recipe)
    profile = load_profile(args.profile)
    t0 = time.perf_counter()
    plan = compile_recipe(recipe, profile)
    t_plan = time.perf_counter() - t0
    sim_s = plan.duration_s
    tmp = Path(tempfile.mkdtemp(prefix="bench_run_"))

    # warm up numba (compiled-code cache load)
    rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
    for _ in rig.run_blocks(plan.x_ref_um[:2000], block_ticks=100):
        pass

    def sim_only():
        rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
        n = 0
        for blk in rig.run_blocks(plan.x_ref_um, block_ticks=100):
            n += blk["t_s"].size
        return n

    def with_log(dtype, threaded=True):
        def run():
            w = TrialLogWriter(tmp / f"bench_{dtype}.mcap", loop_rate_hz=plan.loop_rate_hz, raw_dtype=dtype,
                               threaded=threaded,
                               metadata={"lubricant": recipe.lubricant, "normal_force_N": recipe.normal_force_N},
                               recipe_yaml=recipe.source_text, recipe=recipe.model_dump(mode="json"),
                               profile=profile.model_dump(mode="json"))
            run_sim_trial(plan, recipe, profile, w, None, seed=recipe.seed)
            w.close()
            return w.ticks
        return run

    results = {"recipe": args.recipe, "simulated_s": sim_s, "ticks": plan.n_ticks, "plan_compile_s": t_plan}
    rows = [("sim only (no log)", "sim_only", sim_only),
            ("sim + MCAP log (float64 raw)", "log_float64", with_log("float64")),
            ("  same, writer in caller thread", "log_float64_unthreaded", with_log("float64", threaded=False)),
            ("sim + MCAP log (float32 raw)", "log_float32", with_log("float32"))]
    for label, key, fn in rows:
        r = _measure(fn, args.repeat)
        r["ticks_per_s"] = r["ticks"] / r["wall_s"]
        r["realtime_factor"] = sim_s / r["wall_s"]
        r["cpu_ticks_per_s"] = r["ticks"] / r["cpu_s"] if r["cpu_s"] > 0 else float("nan")
        results[key] = r
        print(f"{label:32s} wall {r['wall_s']:6.2f} s  {r['ticks_per_s']:>10,.0f} ticks/s  "
              f"{r['realtime_factor']:7.1f}x real time   (cpu {r['cpu_s']:.2f} s, "
              f"{r['cpu_ticks_per_s']:,.0f} ticks/cpu-s)")
    for dtype in ("float64", "float32"):
        p = tmp / f"bench_{dtype}.mcap"
        results[f"log_{dtype}"]["file_MB"] = p.stat().st_size / 1e6
        print(f"  file ({dtype} raw): {p.stat().st_size / 1e6:.1f} MB")

    best = None
    out = tmp / "cli.mcap"
    for _ in range(args.repeat):
        w0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "rig.cli", "run", args.recipe, "--sim", "-q", "--out", str(out),
                               "--profile", args.profile], capture_output=True, text=True, cwd=REPO)
        wall = time.perf_counter() - w0
        if proc.returncode != 0:
            print(proc.stderr, file=sys.stderr)
            return 1
        best = wall if best is None else min(best, wall)
    results["rig_run_cli"] = {"wall_s": best, "realtime_factor": sim_s / best, "ticks_per_s": plan.n_ticks / best}
    print(f"{'rig run --sim (fresh process)':32s} wall {best:6.2f} s  {plan.n_ticks / best:>10,.0f} ticks/s  "
          f"{sim_s / best:7.1f}x real time   (startup and plan included)")
    so, l8, l4 = results["sim_only"], results["log_float64"], results["log_float32"]
    print(f"with the log the trial takes x{l8['wall_s'] / so['wall_s']:.1f} the bare loop's wall time "
          f"(x{l8['cpu_s'] / so['cpu_s']:.1f} its CPU time); float32 raw: x{l4['wall_s'] / so['wall_s']:.1f} wall, "
          f"x{l4['cpu_s'] / so['cpu_s']:.1f} CPU")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
