"""A pause that keeps the physics: the velocity-steps recipe on the simulated rig, unpaused and paused
for 30 s between two steps (issue 22, item 5's must-show): A, B, L of each (rig identify's per-step fits,
mean ± s.e. over the steps) and the difference in units of the s.e.

    python benchmarks/bench_pause.py [--hold-s 30] [--seeds 3 4 5] [--json out/bench_pause.json]

The pause is asked for 5 s after the first step (a `PauseControl` script): it takes effect at the next
safe point (the second step's start), holds for --hold-s of trial time, runs up 5 L at the segment's
velocity (1 µm/s), then the plan goes on. Prints the figures beside os.getloadavg().
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def run(seed: int, hold_s: float | None):
    from rig.analysis.identify import identify_trials
    from rig.config.profile import default_profile_path, load_profile
    from rig.config.recipe import compile_recipe, load_recipe
    from rig.session.sim import simulate

    profile = load_profile(default_profile_path())
    recipe = load_recipe(REPO / "config/recipes/velocity-steps.yaml")
    plan = compile_recipe(recipe, profile)
    steps = [e["t_s"] for e in plan.events if e["kind"] == "velocity_step"]
    script = [(steps[0] + 5.0, hold_s)] if hold_s else None
    t0 = time.perf_counter()
    # blocks of 1 s: the script's resume is asked between two blocks (the data do not depend on the block size)
    log, res = simulate(recipe, profile, seed=seed, keep_blocks=True, pause_script=script, block_ticks=1000)
    tr = log.trial_data(25.0)
    ident = identify_trials([tr], whole_record=False)
    r = ident.report()
    pauses = tr.pause_intervals
    return {"seed": seed, "hold_s": hold_s, "status": res.status, "duration_s": res.duration_s,
            "pauses": pauses, "mean": r["mean"], "sem": r["sem"], "n_steps": r["n_steps"],
            "wall_s": time.perf_counter() - t0,
            "events": [(round(e["t_s"], 3), e["kind"]) for e in log.events
                       if e["kind"] in ("pause", "resume", "runup_done", "velocity_step")]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hold-s", type=float, default=30.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[3])
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    load0 = os.getloadavg()
    rows = []
    for seed in a.seeds:
        base, paused = run(seed, None), run(seed, a.hold_s)
        print(f"seed {seed}: unpaused {base['duration_s']:.0f} s ({base['n_steps']} steps), paused "
              f"{paused['duration_s']:.0f} s ({paused['n_steps']} steps), pauses {paused['pauses']}")
        print("   events of the paused run:", paused["events"])
        ok = True
        for p in ("A_mu", "B_mu", "L_um"):
            m0, s0, m1, s1 = base["mean"][p], base["sem"][p], paused["mean"][p], paused["sem"][p]
            se = s0  # the unpaused trial's s.e.
            z = (m1 - m0) / se if se else float("inf")
            ok &= abs(z) <= 1.0
            print(f"   {p:5s} unpaused {m0:.6g} ± {s0:.2g}   paused {m1:.6g} ± {s1:.2g}   "
                  f"difference {z:+.2f} s.e.")
        rows.append({"seed": seed, "unpaused": base, "paused": paused, "within_1_se": bool(ok)})
        print(f"   within 1 s.e.: {ok}")
    print(f"load average {load0[0]:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} CPUs "
          "(a machine shared with other work)")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(rows, indent=2, default=str))
    return 0 if all(r["within_1_se"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
