"""Benchmark: closed-loop ticks per second, real-time factor and log size of the simulated trial, LOGGING INCLUDED.

Runs the paper's velocity-step recipe (config/recipes/velocity-steps.yaml, 681 s
of simulated time, 681 k loop ticks) on the simulated rig, in one sitting:

  1. the closed loop alone (no log; 1 s blocks, as `rig run` uses),
  2. BEFORE: the project's own MCAP writer and the rig.columns.v1 raw channel
     (float64 columns, zstd level -1), loaded from git (``--baseline``, the
     commit before rig/log became a package),
  3. AFTER: rig.log.TrialLogWriter as `rig run` writes it (the ``mcap``
     package's Writer, zstd, rig.columns.v2 device counts, the 25 Hz JSON
     channel with mu, events, loop statistics every second, fsync'd flushes at
     least every second, the writer thread),
  4. the same with the writer in the caller's thread,
  5. the same with a flush after every 1 s block: the chunking of a trial
     logged in real time (hardware), which sets the size per hour a lab keeps,
  6. the whole `rig run RECIPE --sim -q` in a fresh process, and its fixed
     start-up cost (the same command on a 1 s hold).

For each: wall time and CPU time (this process; child CPU for 6), ticks per
second, real-time factor, file size and MB per hour of trial; best of
``--repeat``. The machine is shared: the load average is printed before and
after; CPU figures are the stable ones.

    python benchmarks/bench_run.py [--repeat 3] [--recipe config/recipes/velocity-steps.yaml] [--json out.json]

``--whole [help 'main job' 'one hour'] [--repeat 5] [--vs REF]``: each as a whole ``rig`` process, min /
median / max of ``--repeat`` runs after an uncounted one, wall and CPU (user + system of the process, its
threads included) beside the load average; ``--vs REF`` runs that commit's tree in turn (A B A B), so
before and after are measured in one sitting.

``--threads [WHICH]``: each thread's CPU time (and when it ends) in a whole ``rig run`` process, min of
``--repeat``: the simulation's (main) thread is the critical path, the writer and its zstd thread must keep up.

``--phases``: one (default: one-hour, ``benchmarks/recipes/one-hour-slide.yaml``) trial phase by
phase -- imports, plan, simulation, encoding, compression, fsync, the whole ``rig run`` process -- each
beside the load average, and the log's size per hour in the protobuf and the v2 layouts, with the
simulation's chunks and with real-time ones.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


BASELINE = "5e036b0"  # main before the log package: rig/log.py with its own MCAP writer


def _baseline_writer(commit: str, tmp: Path):
    """TrialLogWriter of rig/log.py at ``commit`` (the project's own MCAP writer), imported from git."""
    src = subprocess.run(["git", "-C", str(REPO), "show", f"{commit}:rig/log.py"], capture_output=True, text=True)
    if src.returncode != 0:
        return None
    path = tmp / "_rig_log_baseline.py"
    path.write_text(src.stdout)
    spec = importlib.util.spec_from_file_location("_rig_log_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["_rig_log_baseline"] = mod
    spec.loader.exec_module(mod)
    return mod.TrialLogWriter


def _log_only(blocks, Baseline, tmp: Path, repeat: int) -> dict:
    """CPU of the log alone on the trial's precomputed blocks, before vs after, interleaved (so that the
    machine's load drifts out), and where the difference goes: raw encoding (v1 vs v2) and the MCAP
    writer (the project's own vs the ``mcap`` package's Writer) on the identical message stream."""
    import io

    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from rig.log import TrialLogWriter
    from rig.log.schemas import ColumnsV2Encoder, device_columns

    def write(cls, name):
        c0 = time.process_time()
        w = cls(tmp / name, threaded=False, fsync=False)
        for b in blocks:
            w.write_block(b)
        w.close()
        return time.process_time() - c0

    best = {"before": [], "after": []}
    for _ in range(repeat):
        best["before"].append(write(Baseline, "lo_before.mcap"))
        best["after"].append(write(TrialLogWriter, "lo_after.mcap"))
    out = {k: min(v) for k, v in best.items()}

    enc = ColumnsV2Encoder(device_columns(), 1000.0)
    old = Baseline(tmp / "enc_v1.mcap", threaded=False, fsync=False)
    t = {"v2": [], "v1": []}
    for _ in range(repeat):
        c0 = time.process_time()
        for b in blocks:
            enc.encode(b, float(b["t_s"][0]))
        t["v2"].append(time.process_time() - c0)
        c0 = time.process_time()
        for b in blocks:
            old._columns_payload(b, float(b["t_s"][0]), b["t_s"].size)
        t["v1"].append(time.process_time() - c0)
    old.close()
    out["encode_v2_s"], out["encode_v1_s"] = min(t["v2"]), min(t["v1"])

    with open(tmp / "lo_after.mcap", "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        msgs = [(m.channel_id, m.log_time, m.data, m.sequence) for _, _, m in reader.iter_messages()]
    own_cls = sys.modules["_rig_log_baseline"]._McapFile
    t = {"mcap": [], "own": []}
    for _ in range(repeat):
        c0 = time.process_time()
        w = Writer(io.BytesIO(), compression=CompressionType.ZSTD)
        w.start()
        ids = {}
        for cid, ch in summary.channels.items():
            sc = summary.schemas.get(ch.schema_id)
            sid = w.register_schema(sc.name, sc.encoding, sc.data) if sc else 0
            ids[cid] = w.register_channel(ch.topic, ch.message_encoding, sid)
        for cid, ns, data, seq in msgs:
            w.add_message(ids[cid], log_time=ns, data=data, publish_time=ns, sequence=seq)
        w.finish()
        t["mcap"].append(time.process_time() - c0)
        c0 = time.process_time()
        o = own_cls(io.BytesIO(), compression="zstd", level=-1)
        o.start("rig-trial", "bench")
        for cid, ch in summary.channels.items():
            o.add_channel(ch.topic, ch.message_encoding, 0)
        o.add_messages(msgs)
        o.finish()
        t["own"].append(time.process_time() - c0)
    out["writer_mcap_s"], out["writer_own_s"] = min(t["mcap"]), min(t["own"])
    out["messages"] = len(msgs)
    return out


def _measure(fn, repeat: int) -> dict:
    """Best (smallest) wall time and best CPU time over ``repeat`` runs of ``fn`` (returns the ticks)."""
    walls, cpus = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        ticks = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return {"wall_s": min(walls), "cpu_s": min(cpus), "ticks": ticks}


def _run_cli(args: list[str], repeat: int) -> dict:
    """Best wall time and best child CPU time (user + sys) of a fresh `python -m rig.cli ...`."""
    best_wall = best_cpu = None
    for _ in range(repeat):
        r0 = os.times()
        w0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "rig.cli", *args], capture_output=True, text=True, cwd=REPO)
        wall = time.perf_counter() - w0
        r1 = os.times()
        if proc.returncode != 0:
            raise SystemExit(f"rig {' '.join(args)} failed:\n{proc.stderr}")
        cpu = (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system)
        best_wall = wall if best_wall is None else min(best_wall, wall)
        best_cpu = cpu if best_cpu is None else min(best_cpu, cpu)
    return {"wall_s": best_wall, "cpu_s": best_cpu}


HOUR_RECIPE = REPO / "benchmarks" / "recipes" / "one-hour-slide.yaml"


def _load() -> str:
    return f"load {os.getloadavg()[0]:.2f}"


def phases(recipe_path: Path, profile_path: Path, out_json: str | None = None) -> dict:
    """Where the time of a (one-hour) simulated trial with its full log goes, phase by phase, each printed
    beside the load average (the machine is shared); and the file's size per hour in each raw layout,
    with the simulation's chunks and with real-time chunks (one per 1 s block, as the hardware writes)."""
    import numpy as np

    res: dict = {"recipe": str(recipe_path)}

    def line(name, wall, cpu, extra=""):
        res[name] = {"wall_s": wall, "cpu_s": cpu}
        print(f"  {name:34s} wall {wall:7.3f} s  cpu {cpu:7.3f} s  {extra:28s} ({_load()})", flush=True)

    print(f"phases of {recipe_path.name} ({_load()}, {os.cpu_count()} cores)")
    w0, r0 = time.perf_counter(), os.times()
    subprocess.run([sys.executable, "-c", "import rig.cli, rig.session.sim, rig.log.writer, rig.log.loopblock"],
                   check=True, cwd=REPO)
    r1 = os.times()
    line("imports (fresh process)", time.perf_counter() - w0,
         (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system))

    from rig.config.profile import load_profile
    from rig.config.recipe import compile_recipe, load_recipe
    from rig.log.loopblock import LoopBlockEncoder
    from rig.log.schemas import ColumnsV2Encoder, device_columns
    from rig.sim import SimRig

    w0, c0 = time.perf_counter(), time.process_time()
    recipe = load_recipe(recipe_path)
    profile = load_profile(profile_path)
    plan = compile_recipe(recipe, profile)
    line("plan (recipe, profile, reference)", time.perf_counter() - w0, time.process_time() - c0)
    hours = plan.duration_s / 3600.0
    rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
    for _ in rig.run_blocks(plan.x_ref_um[:2000], block_ticks=1000, controller=plan.controller):
        pass  # numba's cache loaded
    rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
    from rig.model.feedforward import friction_feedforward_for_plan, initial_velocity_um_s

    w0, c0 = time.perf_counter(), time.process_time()
    ff = friction_feedforward_for_plan(plan.controller, plan.x_ref_um, rig.dt_s, rig.friction_model,
                                       2.0 * rig.normal_force_N,
                                       initial_velocity_um_s(plan.x_ref_um, rig.rate_hz,
                                                             profile.sim.initial_creep_um_s))
    line("friction feed-forward (whole plan)", time.perf_counter() - w0, time.process_time() - c0)
    w0, c0 = time.perf_counter(), time.process_time()
    blocks = [{k: v.copy() for k, v in b.items()}
              for b in rig.run_blocks(plan.x_ref_um, block_ticks=1000, controller=plan.controller, ff_N=ff)]
    line("simulation (closed loop, no log)", time.perf_counter() - w0, time.process_time() - c0,
         f"{plan.n_ticks / 1e6:.2f} M ticks")
    cols = device_columns()
    enc = LoopBlockEncoder(lambda k: cols.get(k, cols["t_s"]), 1000.0)
    enc.plan(tuple(blocks[0]))
    enc.encode(blocks[0], 0.0)
    w0, c0 = time.perf_counter(), time.process_time()
    raw_bytes = sum(len(enc.encode(b, float(b["t_s"][0]))) for b in blocks)
    line("encoding /raw (protobuf)", time.perf_counter() - w0, time.process_time() - c0,
         f"{raw_bytes / 1e6 / hours:.0f} MB/h before zstd")
    v2 = ColumnsV2Encoder(cols, 1000.0)
    w0, c0 = time.perf_counter(), time.process_time()
    for b in blocks:
        v2.encode(b, float(b["t_s"][0]))
    line("  (encoding /raw as rig.columns.v2)", time.perf_counter() - w0, time.process_time() - c0)
    tmp = Path(tempfile.mkdtemp(prefix="bench_phases_"))
    res["sizes_MB_per_hour"] = _log_phases(blocks, tmp, hours, line)
    w0, r0 = time.perf_counter(), os.times()
    subprocess.run([sys.executable, "-m", "rig.cli", "run", str(recipe_path), "--sim", "-q", "--yes", "--out",
                    str(tmp / "whole.mcap")], check=True, cwd=REPO, capture_output=True)
    r1 = os.times()
    line("whole `rig run --sim -q` process", time.perf_counter() - w0,
         (r1.children_user - r0.children_user) + (r1.children_system - r0.children_system),
         f"{plan.duration_s:.0f} s simulated")
    if out_json:
        Path(out_json).write_text(json.dumps(res, indent=2))
    return res


def _log_phases(blocks: list, tmp: Path, hours: float, line) -> dict:
    """The log's phases on the simulated blocks (without compression, zstd, fsync: each the difference
    to the one before), and its size per hour in each raw layout, with the simulation's chunks and with
    real-time ones (one per 1 s block, as the hardware writes)."""
    from rig.log import TrialLogWriter

    def write(name, realtime=False, **kw):
        w = TrialLogWriter(tmp / f"{name}.mcap", threaded=False, **kw)
        w.warm_up()
        w0, c0 = time.perf_counter(), time.process_time()
        for b in blocks:
            w.write_block(b)
            if realtime:
                w.flush()
        w.close()
        size = (tmp / f"{name}.mcap").stat().st_size / 1e6
        return time.perf_counter() - w0, time.process_time() - c0, size / hours

    none = write("none", compression="none", fsync=False)
    line("log without compression/fsync", none[0], none[1], "(encoding, 25 Hz JSON, records)")
    z = write("zstd", fsync=False)
    line("compression (zstd chunks)", z[0] - none[0], z[1] - none[1])
    f = write("fsync")
    line("fsync (every second of wall time)", f[0] - z[0], f[1] - z[1])
    sizes = {"protobuf": f[2]}
    sizes["protobuf, real-time chunks"] = write("rt", realtime=True, fsync=False)[2]
    sizes["v2 (before)"] = write("v2", fsync=False, raw_format="v2")[2]
    sizes["v2 (before), real-time chunks"] = write("v2rt", realtime=True, fsync=False, raw_format="v2")[2]
    blocks = [{k: v for k, v in b.items() if not k.startswith("true_") and k != "spool"} for b in blocks]
    sizes["protobuf, hardware's columns (no sim truths/spool)"] = write("hw", fsync=False)[2]
    sizes["protobuf, hardware's columns, real-time chunks"] = write("hwrt", realtime=True, fsync=False)[2]
    for k, v in sizes.items():
        print(f"  size {k:52s} {v:6.1f} MB per hour of trial")
    return sizes

WHOLE = {"help": ["--help"],
         "main job": ["run", "config/recipes/velocity-steps.yaml", "--sim", "-q", "--yes", "--out", "{out}"],
         "one hour": ["run", "benchmarks/recipes/one-hour-slide.yaml", "--sim", "-q", "--yes", "--out", "{out}"]}


def _checkout(ref: str) -> Path | None:
    """A tree of ``ref`` (git archive) in a temporary directory, run with this venv through PYTHONPATH (its
    numba cache is its own: warmed by the first, uncounted run)."""
    root = Path(tempfile.mkdtemp(prefix=f"bench_run_{ref}_"))
    arch = subprocess.run(["git", "-C", str(REPO), "archive", ref], capture_output=True)
    if arch.returncode != 0:
        return None
    subprocess.run(["tar", "-x", "-C", str(root)], input=arch.stdout, check=True)
    return root


def _one_process(tree: Path, args: list[str], out: Path) -> tuple[float, float]:
    """(wall s, CPU s = user + system) of one fresh ``python -m rig.cli ARGS`` process in ``tree``."""
    if out.exists():
        out.unlink()
    env = {**os.environ, "PYTHONPATH": str(tree)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # both trees with their .pyc, as an installed rig has them
    w0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", *[a.format(out=out) for a in args]], cwd=tree,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - w0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"rig {' '.join(args)} in {tree} exited {proc.returncode}")
    return wall, ru.ru_utime + ru.ru_stime


def _wait_aot_build(tree: Path, timeout_s: float = 300.0) -> None:
    """Wait while ``tree``'s run kernels are being built ahead of time (rig.jitstart.start_aot_build: a
    ``rig_kernels_*.lock`` beside them), so that the counted runs load them; a tree without them returns."""
    folder = Path(os.environ.get("RIG_AOT_DIR") or tree / "rig" / "__pycache__")
    t0 = time.perf_counter()
    while any(folder.glob("rig_kernels_*.lock")) and time.perf_counter() - t0 < timeout_s:
        time.sleep(0.5)


def whole(n: int, which: list[str], ref: str | None) -> dict:
    """Whole-process figures of ``rig --help``, the main job (velocity steps, 655 s) and a one-hour trial:
    min / median / max of ``n`` runs after one uncounted run (numba's cache warm), wall and CPU, each
    beside the load average; with ``ref``, that commit's tree run in turn (A B A B ...) in the same sitting."""
    trees = {"this tree": REPO}
    if ref and Path(ref).is_dir():  # a tree already checked out (e.g. a copy of the other commit)
        trees[Path(ref).name] = Path(ref)
    elif ref:
        t = _checkout(ref)
        if t is None:
            raise SystemExit(f"git archive {ref} failed")
        trees[ref] = t
    out = Path(tempfile.mkdtemp(prefix="bench_run_whole_")) / "t.mcap"
    res: dict = {}
    for name in which:
        args = WHOLE[name]
        runs: dict = {k: [] for k in trees}
        for tree in trees.values():
            _one_process(tree, args, out)  # warm-up: numba's cache, the page cache
            _wait_aot_build(tree)  # and the ahead-of-time kernels a first run builds in the background
        for _ in range(n):
            for k, tree in trees.items():
                runs[k].append(_one_process(tree, args, out))
        for k, rs in runs.items():
            walls, cpus = sorted(r[0] for r in rs), sorted(r[1] for r in rs)
            row = {"wall_s": [walls[0], walls[len(walls) // 2], walls[-1]],
                   "cpu_s": [cpus[0], cpus[len(cpus) // 2], cpus[-1]], "load": os.getloadavg()[0]}
            res[f"{name} ({k})"] = row
            print(f"  rig {name:9s} {k:10s} wall min/median/max {row['wall_s'][0]:6.2f} {row['wall_s'][1]:6.2f} "
                  f"{row['wall_s'][2]:6.2f} s   CPU {row['cpu_s'][0]:6.2f} {row['cpu_s'][1]:6.2f} "
                  f"{row['cpu_s'][2]:6.2f} s   ({_load()})", flush=True)
    return res


# a fresh ``rig`` process that reports, at exit, each thread's CPU time and its start and end (wall s from the
# process's first line): the simulation's (main) thread, the log writer, its zstd thread, the monitor
_THREADS_CODE = r"""
import json, os, sys, threading, time, atexit, runpy
W0 = time.perf_counter()
res = {}
_run = threading.Thread.run
def run(self):
    t0 = time.perf_counter()
    try:
        _run(self)
    finally:
        res[self.name] = {"cpu_s": time.thread_time(), "start_s": t0 - W0, "end_s": time.perf_counter() - W0}
threading.Thread.run = run
def report():
    res["main"] = {"cpu_s": time.thread_time(), "start_s": 0.0, "end_s": time.perf_counter() - W0}
    res["process"] = {"cpu_s": time.process_time(), "start_s": 0.0, "end_s": time.perf_counter() - W0}
    os.write(2, ("RIG_THREADS " + json.dumps(res) + "\n").encode())
atexit.register(report)
sys.argv = ["rig"] + sys.argv[1:]
runpy.run_module("rig.cli", run_name="__main__")
"""


def threads(which: list[str], n: int) -> dict:
    """Each thread's CPU time in a whole ``rig run`` process (the main job, the one-hour trial): the critical
    path is the simulation's (main) thread; the writer and its zstd thread must keep up beside it. Min of
    ``n`` runs after an uncounted one, per thread, beside the load average."""
    out = Path(tempfile.mkdtemp(prefix="bench_run_threads_")) / "t.mcap"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    res: dict = {}
    for name in which:
        args = [a.format(out=out) for a in WHOLE[name]] + ["--overwrite"]
        rows: dict = {}
        for i in range(n + 1):
            p = subprocess.run([sys.executable, "-c", _THREADS_CODE, *args], cwd=REPO, env=env, capture_output=True,
                               text=True)
            line = next((ln for ln in p.stderr.splitlines() if ln.startswith("RIG_THREADS ")), None)
            if p.returncode != 0 or line is None:
                raise SystemExit(f"rig {' '.join(args)} failed:\n{p.stderr[-2000:]}")
            if i:
                for th, v in json.loads(line[len("RIG_THREADS "):]).items():
                    rows.setdefault(th.rstrip("_0123456789"), []).append(v)
        res[name] = {th: {k: min(r[k] for r in v) for k in ("cpu_s", "end_s")} for th, v in rows.items()}
        print(f"  rig {name}: min of {n} ({_load()})")
        for th, v in res[name].items():
            print(f"    {th:22s} CPU {v['cpu_s']:6.2f} s   ends at {v['end_s']:6.2f} s")
    return res


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phases", action="store_true", help="where the time of a one-hour trial goes, phase by "
                    "phase (imports, plan, simulation, encoding, compression, fsync, the whole process), and "
                    "its size per hour in each raw layout (--recipe defaults to the one-hour slide then)")
    ap.add_argument("--recipe", default=str(REPO / "config" / "recipes" / "velocity-steps.yaml"))
    ap.add_argument("--profile", default=str(REPO / "config" / "rigs" / "sim.yaml"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-cli", action="store_true", help="skip the fresh-process runs")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ap.add_argument("--baseline", default=BASELINE, help="git commit whose rig/log.py is the 'before' writer")
    ap.add_argument("--whole", nargs="*", choices=sorted(WHOLE), default=None, metavar="WHICH",
                    help="whole-process figures (min/median/max of --repeat runs, wall and CPU) of: help, "
                         "'main job', 'one hour' (default: all three)")
    ap.add_argument("--threads", nargs="*", choices=sorted(k for k in WHOLE if k != "help"), default=None,
                    metavar="WHICH", help="each thread's CPU time in a whole `rig run` process (min of --repeat "
                    "runs): 'main job', 'one hour' (default: both)")
    ap.add_argument("--vs", default=None, metavar="REF", help="with --whole: run this git commit's tree (or this "
                    "directory's) in turn, in the same sitting (before/after)")
    return ap


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.whole is not None:
        print(f"whole processes, numba cache warm ({_load()}, {os.cpu_count()} cores)")
        res = whole(args.repeat, args.whole or list(WHOLE), args.vs)
        if args.json:
            Path(args.json).write_text(json.dumps(res, indent=2))
        return 0
    if args.threads is not None:
        print(f"threads of whole `rig run` processes, numba cache warm ({_load()}, {os.cpu_count()} cores)")
        res = threads(args.threads or ["main job", "one hour"], args.repeat)
        if args.json:
            Path(args.json).write_text(json.dumps(res, indent=2))
        return 0
    if args.phases:
        rec = Path(args.recipe) if "--recipe" in (argv or sys.argv) else HOUR_RECIPE
        phases(rec, Path(args.profile), args.json)
        return 0
    load0 = os.getloadavg()

    from rig.log import TrialLogWriter
    from rig.config.profile import load_profile
    from rig.config.recipe import load_recipe
    from rig.session import run_trial
    from rig.session.sim import SimBackend
    from rig.sim import SimRig
    from rig.config.recipe import compile_recipe

    recipe = load_recipe(args.recipe)
    profile = load_profile(args.profile)
    t0 = time.perf_counter()
    plan = compile_recipe(recipe, profile)
    t_plan = time.perf_counter() - t0
    sim_s = plan.duration_s
    tmp = Path(tempfile.mkdtemp(prefix="bench_run_"))
    block_ticks = max(1, int(round(recipe.log.block_s * plan.loop_rate_hz)))

    # warm up numba (compiled-code cache load)
    rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
    for _ in rig.run_blocks(plan.x_ref_um[:2000], block_ticks=block_ticks):
        pass

    def sim_only():
        rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
        n = 0
        for blk in rig.run_blocks(plan.x_ref_um, block_ticks=block_ticks):
            n += blk["t_s"].size
        return n

    Baseline = _baseline_writer(args.baseline, tmp)

    def with_log(name, writer_cls=TrialLogWriter, flush_every_block=False, **kw):
        def run():
            w = writer_cls(tmp / f"{name}.mcap", loop_rate_hz=plan.loop_rate_hz,
                           decimated_rate_hz=recipe.log.decimated_rate_hz,
                           metadata={"lubricant": recipe.lubricant, "normal_force_N": recipe.normal_force_N},
                           recipe_yaml=recipe.source_text, recipe=recipe.model_dump(mode="json"),
                           profile=profile.model_dump(mode="json"), **kw)
            if flush_every_block:  # each 1 s block in its own chunk, as in a trial logged in real time
                write = w.write_block

                def write_and_flush(block):
                    write(block)
                    w.flush()
                w.write_block = write_and_flush
            backend = SimBackend(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N,
                                 recipe.seed, block_ticks=block_ticks)
            return run_trial(plan, backend, w, handle_signals=False).ticks
        return run

    results = {"recipe": args.recipe, "simulated_s": sim_s, "ticks": plan.n_ticks, "plan_compile_s": t_plan,
               "cpu_count": os.cpu_count(), "baseline": args.baseline}
    rows = [("closed loop alone (no log)", "sim_only", sim_only)]
    if Baseline is not None:
        rows += [("BEFORE: own writer, columns.v1", "log_before", with_log("log_before", Baseline))]
    rows += [("AFTER: mcap Writer, columns.v2", "log", with_log("log")),
             ("  writer in the caller's thread", "log_unthreaded", with_log("log_unthreaded", threaded=False)),
             ("  a chunk per 1 s block (real time)", "log_realtime_chunks",
              with_log("log_realtime_chunks", flush_every_block=True))]
    if Baseline is not None:
        rows += [("  BEFORE, a chunk per 1 s block", "log_before_realtime_chunks",
                  with_log("log_before_realtime_chunks", Baseline, flush_every_block=True))]
    print(f"{Path(args.recipe).name}: {sim_s:.1f} s simulated, {plan.n_ticks:,} ticks; load average "
          f"{load0[0]:.2f} on {os.cpu_count()} cores; best of {args.repeat}")
    print(f"{'':38s} {'wall':>7s} {'ticks/s':>11s} {'x real time':>11s}   {'CPU':>6s} {'x real time':>11s}"
          f"  {'file':>8s} {'MB/hour':>8s}")
    for label, key, fn in rows:
        r = _measure(fn, args.repeat)
        r["ticks_per_s"] = r["ticks"] / r["wall_s"]
        r["realtime_factor"] = sim_s / r["wall_s"]
        r["cpu_ticks_per_s"] = r["ticks"] / r["cpu_s"] if r["cpu_s"] > 0 else float("nan")
        r["cpu_realtime_factor"] = sim_s / r["cpu_s"] if r["cpu_s"] > 0 else float("nan")
        p = tmp / f"{key}.mcap"
        r["file_MB"] = p.stat().st_size / 1e6 if p.exists() else None
        r["MB_per_hour"] = r["file_MB"] / sim_s * 3600.0 if r["file_MB"] else None
        results[key] = r
        size = f"{r['file_MB']:7.1f}M {r['MB_per_hour']:8.1f}" if r["file_MB"] else ""
        print(f"{label:38s} {r['wall_s']:6.3f}s {r['ticks_per_s']:>11,.0f} {r['realtime_factor']:10.0f}x   "
              f"{r['cpu_s']:5.3f}s {r['cpu_realtime_factor']:10.0f}x  {size}")

    if Baseline is not None:
        blocks = []
        rig = SimRig(profile, profile.friction_model(recipe.lubricant), recipe.normal_force_N, recipe.seed)
        for blk in rig.run_blocks(plan.x_ref_um, block_ticks=block_ticks):
            blocks.append({k: v.copy() for k, v in blk.items()})
        lo = _log_only(blocks, Baseline, tmp, args.repeat)
        results["log_only"] = lo
        print(f"the log alone on the trial's {len(blocks)} blocks (CPU, interleaved, best of {args.repeat}): "
              f"before {lo['before']:.3f} s, after {lo['after']:.3f} s (x{lo['after'] / lo['before']:.2f})")
        print(f"  raw encoding: v1 {lo['encode_v1_s']:.3f} s, v2 {lo['encode_v2_s']:.3f} s; the same "
              f"{lo['messages']:,} messages through the MCAP writer: own {lo['writer_own_s']:.3f} s, "
              f"mcap package {lo['writer_mcap_s']:.3f} s "
              f"({1e6 * lo['writer_mcap_s'] / lo['messages']:.1f} vs {1e6 * lo['writer_own_s'] / lo['messages']:.1f}"
              f" µs per message)")

    if not args.no_cli:
        out = tmp / "cli.mcap"
        cli = _run_cli(["run", args.recipe, "--sim", "-q", "--out", str(out), "--profile", args.profile], args.repeat)
        hold = tmp / "hold.yaml"
        hold.write_text(f"name: hold\nlubricant: {recipe.lubricant}\nsegments:\n  - kind: hold\n    duration_s: 1\n")
        start = _run_cli(["run", str(hold), "--sim", "-q", "--out", str(tmp / "hold.mcap"), "--profile", args.profile],
                         args.repeat)
        cli.update(ticks_per_s=plan.n_ticks / cli["wall_s"], realtime_factor=sim_s / cli["wall_s"],
                   cpu_realtime_factor=sim_s / cli["cpu_s"], startup_wall_s=start["wall_s"],
                   startup_cpu_s=start["cpu_s"])
        results["rig_run_cli"] = cli
        print(f"{'rig run --sim -q (fresh process)':38s} {cli['wall_s']:6.3f}s {cli['ticks_per_s']:>11,.0f} "
              f"{cli['realtime_factor']:10.0f}x   {cli['cpu_s']:5.3f}s {cli['cpu_realtime_factor']:10.0f}x")
        print(f"{'  its fixed start-up (rig run, 1 s hold)':38s} {start['wall_s']:6.3f}s {'':>11s} {'':>11s}   "
              f"{start['cpu_s']:5.3f}s")
        lg = results["log"]
        one_h = start["wall_s"] + 3600.0 / lg["realtime_factor"]
        one_h_cpu = start["cpu_s"] + 3600.0 / lg["cpu_realtime_factor"]
        results["one_hour_trial_estimate"] = {"wall_s": one_h, "cpu_s": one_h_cpu}
        print(f"a one-hour trial with `rig run` ~ {one_h:.1f} s wall, {one_h_cpu:.1f} s CPU "
              f"(start-up + 3600 s at the logged rate)")
    so, lg = results["sim_only"], results["log"]
    line = f"the log adds x{lg['cpu_s'] / so['cpu_s']:.2f} to the bare loop's CPU time"
    if "log_before" in results:
        bf = results["log_before"]
        results["after_vs_before_cpu"] = lg["cpu_s"] / bf["cpu_s"]
        line += (f" (before: x{bf['cpu_s'] / so['cpu_s']:.2f}); sim+log throughput after/before "
                 f"{bf['cpu_s'] / lg['cpu_s']:.2f} (CPU), {bf['wall_s'] / lg['wall_s']:.2f} (wall)")
    print(line)
    rt = results["log_realtime_chunks"]
    print(f"size of a trial logged in real time: {rt['MB_per_hour']:.1f} MB per hour of 1 kHz trial (target <= 60)"
          + (f"; before {results['log_before_realtime_chunks']['MB_per_hour']:.1f}"
             if "log_before_realtime_chunks" in results else ""))
    load1 = os.getloadavg()
    results["loadavg_before_after"] = [load0[0], load1[0]]
    print(f"load average after: {load1[0]:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
