"""Before/after benchmark of two checkouts of rig (issue 8: the re-layout), run in one sitting.

    python benchmarks/bench_compare.py --before /work/before --after . [--quick] [--repeat N] [--md FILE]

Each tree is measured through its own venv (``<tree>/.venv/bin/rig``, ``<tree>/.venv/bin/python``,
cwd = the tree), never by importing it here, so the two module layouts need not agree. Timed
steps run INTERLEAVED, before/after then after/before (ABBA), ``--repeat`` times, so machine drift
hits both trees alike; best and median are reported, the ratio after/before is of the bests.

Quantities (a step that fails in one tree prints ``failed: <reason>`` in its cell and the run goes on):

1. closed-loop simulation speed without the log: ``SimRig(None, "boundary")`` (the tree's
   config/rigs/sim.yaml) through ``run_blocks`` (100-tick blocks) on one fixed reference,
   1 h (--quick: 10 min) at 1 kHz of 1 and 10 µm/s velocity steps (benchmarks/bench_sim.py's),
   numba warm-up excluded: ticks/s and x real time by wall and by the process's CPU time;
2. with the log: ``rig run config/recipes/velocity-steps.yaml --sim --out T.mcap -q``, whole-process
   wall time, the simulated duration (the recipes differ a little between trees) and
   simulated/wall (x real time);
3. ``rig identify T.mcap --json J`` wall time, each tree on its own trial;
4. ``rig diagnose`` wall time on ../shared/data/real/leeman-p4309-step2.csv and on the 25 Hz
   CSV export of T.mcap, with the causes found;
5. each tree's ``benchmarks/bench_diagnose.py accuracy N`` and ``clean M``: named / within 25 %
   per cause and the false-finding count. A tree whose bench_diagnose takes a NOISE_SCALE
   argument (after the re-layout: 1 = the profile's noise, the paper's ± read as 2 sigma) runs
   with ``--noise-scale`` (default 2: the paper's ± as 1 sigma, the noise the earlier generator
   used), so both trees see records of the same noise level;
6. Table 2: ``rig reproduce --trials K --json J``: recovered mean A_mu, B_mu, L_um per lubricant
   beside the paper's;
7. loop timing: ``rig loop-bench --seconds S --hardware P --json J``, P the tree's
   config/rigs/emulated.yaml with private ports and run directory (other processes on this
   machine may run their own emulators on the default ones): execution p50/p99, lateness p99,
   skipped cycles.

--quick: repeat 1, accuracy 1 seed, clean 3, reproduce 2 trials, loop 5 s.
Default: repeat 3, accuracy 3 seeds, clean 12, reproduce 4 trials, loop 20 s.
The load average is printed at start and end (and per step on stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SIM_SNIPPET = r'''
import json, sys, time
import numpy as np
from rig.sim import SimRig          # a module before the re-layout, a package after: same name

def reference(minutes, rate_hz=1000.0, x_lo_um=1000.0, x_hi_um=4000.0):
    n = int(round(minutes * 60.0 * rate_hz)); dt = 1.0 / rate_hz
    x = np.empty(n); pos = x_lo_um; direction = 1.0; i = 0; k = 0
    while i < n:
        v = (1.0, 10.0)[k % 2]
        m = min(n - i, int(round(250.0 / v / dt)))
        seg = pos + direction * v * dt * np.arange(1, m + 1)
        x[i:i + m] = seg; pos = seg[-1]; i += m; k += 1
        if (direction > 0 and pos >= x_hi_um) or (direction < 0 and pos <= x_lo_um):
            direction = -direction
    return x

xref = reference(float(sys.argv[1]))
for _ in SimRig(None, "boundary", seed=0).run_blocks(xref[:5000]):   # numba compile / cache load
    pass
rig = SimRig(None, "boundary", seed=0)
t0, c0 = time.perf_counter(), time.process_time()
ticks = 0
for block in rig.run_blocks(xref, block_ticks=100):
    ticks += block["t_s"].size
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
assert ticks == xref.size, (ticks, xref.size)
print(json.dumps({"ticks": ticks, "sim_s": ticks * rig.dt_s, "wall_s": wall, "cpu_s": cpu}))
'''

LUBRICANTS = ("dry", "paraffin", "boundary")


class StepFailed(Exception):
    pass


def load() -> str:
    a = os.getloadavg()
    return f"{a[0]:.2f} {a[1]:.2f} {a[2]:.2f}"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')} load {load()}] {msg}", file=sys.stderr, flush=True)


def run(tree: Path, args: list[str], timeout: float, what: str) -> tuple[float, str]:
    """Run ``args`` (first item 'rig' or 'python' = the tree's venv) in ``tree``; (wall s, stdout+stderr)."""
    exe = tree / ".venv" / "bin" / args[0]
    if not exe.exists():
        raise StepFailed(f"no {exe}")
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1", PYTHONUNBUFFERED="1")
    env.pop("VIRTUAL_ENV", None)
    t0 = time.perf_counter()
    try:
        p = subprocess.run([str(exe), *args[1:]], cwd=tree, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        raise StepFailed(f"{what}: timed out after {timeout:g} s") from None
    wall = time.perf_counter() - t0
    out = p.stdout + p.stderr
    if p.returncode != 0:
        lines = [ln.strip() for ln in out.splitlines() if ln.strip() and not set(ln.strip()) <= set("│╰─╯╭╮ ")]
        tail = lines[-1] if lines else "no output"
        raise StepFailed(f"{what}: exit {p.returncode}: {tail[:160]}")
    return wall, out


class Cell:
    """Samples of one quantity in one tree, or the reason it failed."""

    def __init__(self):
        self.values: list[float] = []
        self.error: str | None = None
        self.text: str | None = None

    def add(self, v: float) -> None:
        self.values.append(float(v))

    def best(self, higher_is_better: bool) -> float | None:
        if not self.values:
            return None
        return max(self.values) if higher_is_better else min(self.values)


def fmt(v: float) -> str:
    if v == int(v) and abs(v) < 1e4:
        return str(int(v))
    a = abs(v)
    if a >= 1e4:
        return f"{v:,.0f}"
    if a >= 100:
        return f"{v:.0f}"
    if a >= 10:
        return f"{v:.1f}"
    return f"{v:.3g}"


class Table:
    def __init__(self):
        self.rows: list[tuple[str, Cell, Cell, bool | None, str]] = []

    def add(self, name: str, before: Cell, after: Cell, higher_is_better: bool | None = None, unit: str = ""):
        self.rows.append((name, before, after, higher_is_better, unit))

    @staticmethod
    def cell_text(c: Cell, hib: bool | None, unit: str) -> str:
        if c.error and not c.values and c.text is None:
            return f"failed: {c.error}".replace("|", "/")
        if c.text is not None:
            s = c.text
        elif not c.values:
            s = "-"
        elif len(c.values) == 1 or hib is None:
            s = fmt(c.values[0]) + unit
        else:
            s = f"{fmt(c.best(hib))}{unit} (median {fmt(statistics.median(c.values))})"
        if c.error:
            s += f" (also failed once: {c.error})"
        return s.replace("|", "/")

    def markdown(self) -> str:
        out = ["| quantity | before | after | after/before |", "|---|---|---|---|"]
        for name, b, a, hib, unit in self.rows:
            ratio = ""
            if hib is not None and b.values and a.values and b.best(hib):
                ratio = f"{a.best(hib) / b.best(hib):.2f}"
            out.append(f"| {name} | {self.cell_text(b, hib, unit)} | {self.cell_text(a, hib, unit)} | {ratio} |")
        return "\n".join(out)


def interleave(trees: dict[str, Path], repeat: int):
    """(rep, label, tree) in ABBA order: before, after, after, before, ..."""
    names = list(trees)
    for r in range(repeat):
        for lab in (names if r % 2 == 0 else names[::-1]):
            yield r, lab, trees[lab]


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def private_emulated_profile(tree: Path, work: Path) -> Path:
    """The tree's config/rigs/emulated.yaml with its own Modbus/CAN ports and pty directory."""
    src = tree / "config" / "rigs" / "emulated.yaml"
    text = src.read_text()
    run_dir = work / "emu"
    run_dir.mkdir(parents=True, exist_ok=True)
    text = re.sub(r"^extends:\s*(\S+)", lambda m: f"extends: {(src.parent / m.group(1)).resolve()}", text, flags=re.M)
    text = re.sub(r"(port:\s*)15502\b", lambda m: f"{m.group(1)}{free_port(socket.SOCK_STREAM)}", text)
    text = re.sub(r"(port:\s*)43113\b", lambda m: f"{m.group(1)}{free_port(socket.SOCK_DGRAM)}", text)
    text = text.replace("/tmp/rig-emulated", str(run_dir))
    dst = work / "emulated-private.yaml"
    dst.write_text(text)
    return dst


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True, help="checkout before the change (with .venv)")
    ap.add_argument("--after", type=Path, required=True, help="checkout after the change (with .venv)")
    ap.add_argument("--quick", action="store_true", help="small counts (see the module docstring)")
    ap.add_argument("--repeat", type=int, default=None, help="repeats of the timed steps (default 3, quick 1)")
    ap.add_argument("--noise-scale", type=float, default=2.0,
                    help="NOISE_SCALE for a bench_diagnose.py that takes one (default 2: the earlier generator's noise)")
    ap.add_argument("--md", type=Path, default=None, help="also write the markdown here")
    ap.add_argument("--keep", action="store_true", help="keep the work directory (trial logs, JSON)")
    args = ap.parse_args()

    q = args.quick
    repeat = args.repeat or (1 if q else 3)
    n_acc, n_clean, n_rep, loop_s = (1, 3, 2, 5.0) if q else (3, 12, 4, 20.0)
    sim_minutes = 10.0 if q else 60.0
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    for lab, t in trees.items():
        if not (t / ".venv" / "bin" / "rig").exists():
            print(f"error: --{lab} {t}: no .venv/bin/rig there (python3 -m venv .venv && .venv/bin/pip install -e .)",
                  file=sys.stderr)
            return 2
    real_csv = (trees["after"].parent / "shared" / "data" / "real" / "leeman-p4309-step2.csv")
    if not real_csv.exists():
        real_csv = (trees["before"].parent / "shared" / "data" / "real" / "leeman-p4309-step2.csv")
    work = Path(tempfile.mkdtemp(prefix="bench_compare-"))
    t_start = time.time()
    load_start = load()
    log(f"work dir {work}; repeat {repeat}; trees {trees}")
    table = Table()

    def cells():
        return {"before": Cell(), "after": Cell()}

    def row(name, c, hib=None, unit=""):
        table.add(name, c["before"], c["after"], hib, unit)

    # 1. closed-loop simulation speed, no log
    snippet = work / "sim_speed.py"
    snippet.write_text(SIM_SNIPPET)
    ticks_s, xrt, xrt_cpu = cells(), cells(), cells()
    for r, lab, tree in interleave(trees, repeat):
        log(f"sim speed {lab} #{r + 1}")
        try:
            _, out = run(tree, ["python", str(snippet), str(sim_minutes)], 1800, "sim speed")
            d = json.loads(out.strip().splitlines()[-1])
            ticks_s[lab].add(d["ticks"] / d["wall_s"])
            xrt[lab].add(d["sim_s"] / d["wall_s"])
            xrt_cpu[lab].add(d["sim_s"] / d["cpu_s"])
        except (StepFailed, ValueError, KeyError) as e:
            ticks_s[lab].error = xrt[lab].error = xrt_cpu[lab].error = str(e)
    row(f"sim closed loop, no log ({sim_minutes:g} min at 1 kHz, run_blocks): ticks/s", ticks_s, True)
    row("sim closed loop, no log: x real time (wall)", xrt, True, "x")
    row("sim closed loop, no log: x real time (CPU time of the process)", xrt_cpu, True, "x")

    # 2. rig run --sim (with the log)
    run_wall, run_sim, run_xrt, run_loop_xrt = cells(), cells(), cells(), cells()
    mcap = {lab: work / f"{lab}.mcap" for lab in trees}
    for r, lab, tree in interleave(trees, repeat):
        log(f"rig run {lab} #{r + 1}")
        out_path = mcap[lab] if r == 0 else work / f"{lab}-{r}.mcap"
        try:
            wall, out = run(tree, ["rig", "run", "config/recipes/velocity-steps.yaml", "--sim", "--out", str(out_path),
                                   "-q"], 3600, "rig run")
            m = re.search(r"simulated/trial time\s+([\d.,]+)\s*s", out)
            if not m:
                raise StepFailed("rig run: no 'simulated/trial time' in its output")
            sim_s = float(m.group(1).replace(",", ""))
            run_wall[lab].add(wall)
            run_sim[lab].add(sim_s)
            run_xrt[lab].add(sim_s / wall)
            m = re.search(r"([\d.,]+)x real time", out)
            if m:
                run_loop_xrt[lab].add(float(m.group(1).replace(",", "")))
            if r > 0:
                out_path.unlink(missing_ok=True)
        except StepFailed as e:
            for c in (run_wall, run_sim, run_xrt, run_loop_xrt):
                c[lab].error = str(e)
    for lab in trees:
        if mcap[lab].exists():
            run_sim[lab].text = f"{run_sim[lab].values[0]:.1f} s, log {mcap[lab].stat().st_size / 1e6:.1f} MB" \
                if run_sim[lab].values else None
    row("`rig run velocity-steps --sim` (with the log): simulated duration, log size", run_sim)
    row("`rig run` whole-process wall time", run_wall, False, " s")
    row("`rig run` x real time (simulated / whole-process wall)", run_xrt, True, "x")
    row("`rig run` x real time as the command reports it (loop only)", run_loop_xrt, True, "x")

    # 3. identify
    id_wall, id_A = cells(), cells()
    for r, lab, tree in interleave(trees, repeat):
        log(f"identify {lab} #{r + 1}")
        if not mcap[lab].exists():
            id_wall[lab].error = "no trial (rig run failed)"
            continue
        try:
            j = work / f"{lab}-identify.json"
            wall, _ = run(tree, ["rig", "identify", str(mcap[lab]), "--json", str(j)], 3600, "rig identify")
            id_wall[lab].add(wall)
        except StepFailed as e:
            id_wall[lab].error = str(e)
    row("`rig identify T.mcap --json` wall time", id_wall, False, " s")

    # 4. diagnose: real record and the 25 Hz export of the trial
    csv25 = {}
    for lab, tree in trees.items():
        if mcap[lab].exists():
            try:
                csv25[lab] = work / f"{lab}-25hz.csv"
                run(tree, ["rig", "export", str(mcap[lab]), "--csv", str(csv25[lab]), "--rate", "25"], 600, "rig export")
            except StepFailed as e:
                csv25[lab] = e
    for what, src in (("real leeman-p4309-step2.csv", lambda lab: real_csv), ("25 Hz export of T.mcap", csv25.get)):
        wall, causes = cells(), cells()
        for r, lab, tree in interleave(trees, repeat):
            log(f"diagnose {what} {lab} #{r + 1}")
            f = src(lab)
            if not isinstance(f, Path) or not f.exists():
                wall[lab].error = causes[lab].error = f"no input ({f})"
                continue
            try:
                j = work / f"{lab}-diag.json"
                w, _ = run(tree, ["rig", "diagnose", str(f), "--json", str(j)], 3600, "rig diagnose")
                wall[lab].add(w)
                rep = json.loads(j.read_text())
                found = [x["cause"] for x in rep.get("findings", [])] + \
                        [f"unexplained({u.get('follows', '?')})" for u in rep.get("unexplained", [])]
                causes[lab].text = ", ".join(found) or "nothing"
            except (StepFailed, ValueError, KeyError, OSError) as e:
                wall[lab].error = causes[lab].error = str(e)
        row(f"`rig diagnose` wall time, {what}", wall, False, " s")
        row(f"`rig diagnose` findings, {what}", causes)

    # 5. bench_diagnose accuracy and clean (results, not timing: once per tree, interleaved)
    acc = {lab: {} for lab in trees}
    acc_err: dict[str, str] = {}
    clean = cells()
    bd_wall = {"accuracy": cells(), "clean": cells()}
    for kind, n in (("accuracy", n_acc), ("clean", n_clean)):
        for _, lab, tree in interleave(trees, 1):
            log(f"bench_diagnose {kind} {n} {lab}")
            script = tree / "benchmarks" / "bench_diagnose.py"
            cmd = ["python", "benchmarks/bench_diagnose.py", kind, str(n)]
            takes_noise = script.exists() and "NOISE_SCALE" in script.read_text()
            if takes_noise:
                cmd.append(f"{args.noise_scale:g}")
            try:
                w, out = run(tree, cmd, 7200, f"bench_diagnose {kind}")
                bd_wall[kind][lab].add(w)
                if kind == "accuracy":
                    for m in re.finditer(r"^(\w+)\s+named (\d+)/(\d+), within 25 %: (\d+)/(\d+), "
                                         r"median worst-param error (\S+) %", out, re.M):
                        acc[lab][m.group(1)] = f"{m.group(2)}/{m.group(3)}, {m.group(4)}/{m.group(5)}"
                    if not acc[lab]:
                        raise StepFailed("bench_diagnose accuracy: no 'named a/n' lines in its output")
                else:
                    m = re.search(r"false-finding rate: (\d+)/(\d+)", out)
                    if not m:
                        raise StepFailed("bench_diagnose clean: no 'false-finding rate' in its output")
                    clean[lab].add(int(m.group(1)))
                    clean[lab].text = f"{m.group(1)}/{m.group(2)} records" + \
                                      (f" (noise scale {args.noise_scale:g})" if takes_noise else "")
            except StepFailed as e:
                if kind == "accuracy":
                    acc_err[lab] = str(e)
                else:
                    clean[lab].error = str(e)
    causes = list(dict.fromkeys([*acc["before"], *acc["after"]]))
    for cause in causes or ["(all causes)"]:
        c = cells()
        for lab in trees:
            if lab in acc_err:
                c[lab].error = acc_err[lab]
            else:
                c[lab].text = acc[lab].get(cause, "-")
        row(f"bench_diagnose accuracy {n_acc} seed(s), {cause}: named, within 25 %", c)
    row(f"bench_diagnose clean {n_clean}: records with a false finding", clean)
    row(f"bench_diagnose accuracy {n_acc} wall time (9 causes)", bd_wall["accuracy"], False, " s")
    row(f"bench_diagnose clean {n_clean} wall time", bd_wall["clean"], False, " s")

    # 6. Table 2
    rep = {}
    rep_wall = cells()
    for _, lab, tree in interleave(trees, 1):
        log(f"reproduce --trials {n_rep} {lab}")
        j = work / f"{lab}-reproduce.json"
        try:
            w, _ = run(tree, ["rig", "reproduce", "--trials", str(n_rep), "--json", str(j)], 7200, "rig reproduce")
            rep_wall[lab].add(w)
            rep[lab] = json.loads(j.read_text())
        except (StepFailed, ValueError, OSError) as e:
            rep_wall[lab].error = str(e)
    for lub in LUBRICANTS:
        c = cells()
        paper = None
        for lab in trees:
            try:
                r = rep[lab]["lubricants"][lub]
                m = r["recovered"]["mean"]
                c[lab].text = f"{m['A_mu']:.5f} / {m['B_mu']:.5f} / {m['L_um']:.1f}"
                tr = r.get("truth", {}).get("mean")
                if tr:
                    c[lab].text += f" (trials' truth {tr['A_mu']:.5f} / {tr['B_mu']:.5f} / {tr['L_um']:.1f})"
                paper = paper or r["paper"]
            except KeyError as e:
                c[lab].error = rep_wall[lab].error or f"no {e} in the reproduce JSON"
        ptxt = (f"{paper['A_mu']['mean']:.5f} / {paper['B_mu']['mean']:.5f} / {paper['L_um']['mean']:.1f}"
                if paper else "?")
        row(f"Table 2 {lub}, {n_rep} trials: A_mu / B_mu / L_um (paper: {ptxt})", c)
    row(f"`rig reproduce --trials {n_rep}` wall time", rep_wall, False, " s")

    # 7. loop timing
    lp = {k: cells() for k in ("exec_p50_us", "exec_p99_us", "late_p99_us", "skipped")}
    for r, lab, tree in interleave(trees, repeat):
        log(f"loop-bench {loop_s:g} s {lab} #{r + 1}")
        d = work / f"{lab}-loop"
        d.mkdir(exist_ok=True)
        j = d / "loop.json"
        try:
            prof = private_emulated_profile(tree, d)
            _, out = run(tree, ["rig", "loop-bench", "--seconds", f"{loop_s:g}", "--hardware", str(prof),
                                "--json", str(j)], 600 + 5 * loop_s, "rig loop-bench")
            try:
                res = json.loads(j.read_text())
                vals = {k: res[k] for k in lp}
            except (OSError, ValueError, KeyError):   # from the text: 'exec p50 X µs p99 Y µs', 'lateness ... p99 Z'
                flat = " ".join(out.split())
                m_e = re.search(r"exec\s+p50\s+([\d.]+)\s*µs\s+p99\s+([\d.]+)", flat)
                m_l = re.search(r"lateness\s+p50\s+[\d.]+\s*µs\s+p99\s+([\d.]+)", flat)
                m_s = re.search(r"(\d+) skipped", flat)
                if not (m_e and m_l and m_s):
                    raise StepFailed("rig loop-bench: figures not found in its JSON or output")
                vals = {"exec_p50_us": float(m_e.group(1)), "exec_p99_us": float(m_e.group(2)),
                        "late_p99_us": float(m_l.group(1)), "skipped": int(m_s.group(1))}
            for k, v in vals.items():
                lp[k][lab].add(v)
        except StepFailed as e:
            for c in lp.values():
                c[lab].error = str(e)
    row(f"loop-bench {loop_s:g} s: execution p50", lp["exec_p50_us"], False, " µs")
    row(f"loop-bench {loop_s:g} s: execution p99", lp["exec_p99_us"], False, " µs")
    row(f"loop-bench {loop_s:g} s: lateness p99", lp["late_p99_us"], False, " µs")
    row(f"loop-bench {loop_s:g} s: skipped cycles (of {int(loop_s * 1000)})", lp["skipped"], False)

    load_end = load()
    minutes = (time.time() - t_start) / 60.0
    text = [f"bench_compare {'--quick ' if q else ''}(repeat {repeat}, timed steps interleaved ABBA; "
            f"best (median) of the repeats; after/before of the bests)",
            f"before: {trees['before']}  after: {trees['after']}",
            f"started {time.strftime('%Y-%m-%d %H:%M', time.gmtime(t_start))} UTC, took {minutes:.1f} min on "
            f"{os.cpu_count()} CPUs",
            f"load average (1/5/15 min) at start: {load_start}; at end: {load_end}", "",
            table.markdown()]
    md = "\n".join(text)
    print(md)
    if args.md:
        args.md.write_text(md + "\n")
    if args.keep:
        log(f"kept {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
