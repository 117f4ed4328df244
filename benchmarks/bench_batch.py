"""Speed-up of the batch engine (rig.catalog.batch) on this machine's cores, and the figures
docs/scaling.md projects from.

    python benchmarks/bench_batch.py                 # everything, 2 workers
    python benchmarks/bench_batch.py reproduce       # rig reproduce: 3 lubricants x 8 simulated trials
    python benchmarks/bench_batch.py identify        # a 50-file identify batch (paper-protocol trials)
    python benchmarks/bench_batch.py overhead        # scheduler overhead per task (no-op tasks)
    python benchmarks/bench_batch.py catalog         # indexing, unchanged-file check, result writes
    python benchmarks/bench_batch.py cli             # the commands end to end: `rig reproduce` and
                                                     # `rig identify DIR`, --jobs 1 against --jobs N
    python benchmarks/bench_batch.py sizes           # `rig reproduce` at five batch sizes (1-30 s),
                                                     # --jobs 1 against --jobs N, fresh processes
    options: --jobs N (default 2), --files N (default 50), --trials N (default 8), --rounds N
             (default 2; cli and reproduce), --json OUT

Each figure is printed with the load average (1, 5, 15 min) before and after, because the
machine may be shared: a speed-up below the core count on a loaded machine says as much
about the other processes as about the engine. Two speed-ups are given:

- *warm*: the cluster is up and its workers have imported rig and compiled its numba code
  (a warm-up map runs first); this is what a long batch sees after its first seconds;
- *end to end*: including the start of the LocalCluster and the workers' first imports.
The serial run is in this process, also warmed up first.

``cli`` measures what a user sees: the same command with ``--jobs 1`` (serial, in-process, no
Dask: the honest baseline) and with ``--jobs N`` as fresh processes, interleaved (1, N, N, 1,
...), with the CPU time of each command and its children (the workers) beside its wall time.
Both pay Python's start and rig's imports; the parallel one also the LocalCluster's start.
"""

from __future__ import annotations

import os

# one thread per process on both sides: Dask starts its workers with these set to 1, so the
# serial reference must too, or its BLAS calls would use a second core and the comparison
# would not be one core against N
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import contextlib  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from rig.catalog.batch import Engine, dask_client, run_tasks  # noqa: E402


@contextlib.contextmanager
def _warm_engine(jobs: int):
    """The engine a `rig` command uses (this process and jobs - 1 forked workers), told to start its
    workers whatever the work (start cost 0), so that the warm-up map starts them."""
    eng = Engine(jobs, start_cost_s=0.0)
    try:
        yield eng
    finally:
        eng.close()


def load() -> str:
    a, b, c = os.getloadavg()
    return f"load {a:.2f} {b:.2f} {c:.2f}"


def autogroup() -> str:
    """Linux's per-session CPU sharing: with it on, this session's processes (the workers
    included) share one session's slice of a busy machine, so a loaded machine caps the
    speed-up whatever the number of workers."""
    try:
        on = Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return "autogroup unknown"
    return "autogroup on (CPU shared per session)" if on else "autogroup off"


def _noop(x):
    return x


def _mk_files(n: int, root: Path) -> list[Path]:
    """n paper-protocol trials (steps 1->2, 1->5, 1->10 µm/s; 25 Hz) as CSVs, Table-2 lubricants."""
    from rig.sim import synth
    from rig.data import write_csv
    from rig.model.spec import FrictionModel

    out = []
    lubs = ("boundary", "dry", "paraffin")
    for k in range(n):
        lub = lubs[k % 3]
        tr = synth.generate(FrictionModel.for_lubricant(lub, 0.12), synth.paper_step_protocol(), seed=k,
                            lubricant=lub).trial
        tr.metadata["lubricant"] = lub
        p = root / f"trial{k:03d}.csv"
        write_csv(tr, p)
        out.append(p)
    return out


def bench_identify(jobs: int, n_files: int) -> dict:
    from rig.catalog.tasks import identify_file

    with tempfile.TemporaryDirectory() as d:
        files = _mk_files(n_files, Path(d))
        mb = sum(p.stat().st_size for p in files) / 1e6
        items = [(str(p), {}) for p in files]
        run_tasks(identify_file, items[:1], jobs=1)  # warm-up: imports, numba cache
        print(f"identify: {n_files} files ({mb:.1f} MB CSV), {load()}")
        # interleaved rounds (serial, then the same files on the warm cluster) so that a change
        # of the machine's load hits both sides alike
        rounds = [items[i:i + 10] for i in range(0, len(items), 10)]
        serial, par, t_serial, t_warm = [], [], 0.0, 0.0
        t0 = time.perf_counter()
        with _warm_engine(jobs) as client:
            t_start = time.perf_counter() - t0
            run_tasks(identify_file, items[:jobs * 2], client=client)  # warm-up on every worker
            for rd in rounds:
                t = time.perf_counter()
                serial += run_tasks(identify_file, rd, jobs=1)
                t_serial += time.perf_counter() - t
                t = time.perf_counter()
                par += run_tasks(identify_file, rd, client=client)
                t_warm += time.perf_counter() - t
            # the whole batch at once on the warm cluster (the rounds of 10 above pay the tail of
            # each round: 5 tail waits instead of 1), alternated with the whole batch serially
            whole_s, whole_p = [], []
            for _ in range(2):
                t = time.perf_counter()
                run_tasks(identify_file, items, jobs=1)
                whole_s.append(time.perf_counter() - t)
                t = time.perf_counter()
                run_tasks(identify_file, items, client=client)
                whole_p.append(time.perf_counter() - t)
        per_task = [r.seconds for r in serial]
        print(f"  serial: {t_serial:.2f} s ({t_serial / n_files * 1e3:.0f} ms per file), {load()}")
        # end to end: a fresh cluster, cold workers, the whole batch
        t0 = time.perf_counter()
        run_tasks(identify_file, items, jobs=jobs)
        t_e2e = time.perf_counter() - t0
        same = all(json.dumps(_strip(a.value), sort_keys=True) == json.dumps(_strip(b.value), sort_keys=True)
                   for a, b in zip(serial, par))
        busy = sum(r.seconds for r in par)
        cpu_s, cpu_p = sum(r.cpu_seconds for r in serial), sum(r.cpu_seconds for r in par)
        print(f"  {jobs} workers busy {busy:.2f} s in {t_warm:.2f} s of wall: {busy / t_warm:.2f} tasks running "
              f"on average (ideal {jobs}); CPU time serial {cpu_s:.2f} s, on the workers {cpu_p:.2f} s "
              f"(the workers got {cpu_p / t_warm:.2f} cores)")
        print(f"  {jobs} workers, warm: {t_warm:.2f} s -> speed-up {t_serial / t_warm:.2f}x; "
              f"end to end (cluster start {t_start:.1f} s): {t_e2e:.2f} s -> {t_serial / t_e2e:.2f}x; "
              f"results identical: {same}; {load()}")
        print(f"  the whole {n_files}-file batch at once, warm cluster, alternated with serial: serial "
              f"{', '.join(f'{x:.2f}' for x in whole_s)} s, {jobs} workers {', '.join(f'{x:.2f}' for x in whole_p)} s "
              f"-> speed-up {min(whole_s) / min(whole_p):.2f}x best, "
              f"{sorted(a / b for a, b in zip(whole_s, whole_p))[0]:.2f}x worst pair; {load()}")
        return {"n_files": n_files, "whole_serial_s": whole_s, "whole_parallel_s": whole_p, "csv_MB": mb, "serial_s": t_serial, "warm_s": t_warm, "end_to_end_s": t_e2e,
                "cluster_start_s": t_start, "per_task_s_mean": sum(per_task) / len(per_task),
                "per_task_s_max": max(per_task), "speedup_warm": t_serial / t_warm,
                "speedup_end_to_end": t_serial / t_e2e, "identical": same, "jobs": jobs,
                "worker_busy_s": busy, "cpu_serial_s": cpu_s, "cpu_workers_s": cpu_p,
                "load_after": os.getloadavg()}


def _strip(x):
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if k not in ("fit_time_s", "sim_s")}
    if isinstance(x, list):
        return [_strip(v) for v in x]
    return x


def bench_reproduce(jobs: int, n_trials: int, rounds: int = 2) -> dict:
    """``reproduce()`` warm: the whole run (3 lubricants x n_trials, one map, longest first), serial
    in this process against the warm cluster, interleaved (S P P S ...)."""
    from rig.analysis.reproduce import reproduce
    from rig.catalog.batch import run_tasks as _rt

    seen: list = []

    def map_on(client):
        def _m(fn, items, cost=None):
            res = _rt(fn, items, client=client, cost=cost)
            seen.extend(res)
            assert all(r.ok for r in res), [r.error for r in res if not r.ok]
            return [r.value for r in res]
        return _m

    def serial_map(fn, items, cost=None):
        res = _rt(fn, items, jobs=1)
        seen.extend(res)
        return [r.value for r in res]

    reproduce(2, seed=99, map_fn=serial_map)  # warm-up here (numba cache, imports)
    print(f"reproduce: 3 lubricants x {n_trials} simulated trials (full simulated rig), {autogroup()}, {load()}")
    t_serial, t_warm, cpu_serial, cpu_warm, span_warm = [], [], [], [], []
    cold = _cold_reproduce(jobs, n_trials, seen)
    t0 = time.perf_counter()
    with _warm_engine(jobs) as client:
        t_start = time.perf_counter() - t0
        reproduce(2 * jobs, seed=99, map_fn=map_on(client))  # warm every worker, every lubricant
        serial = par = None
        for k in range(2 * rounds):
            side = "serial" if k % 4 in (0, 3) else "parallel"
            seen.clear()
            t = time.perf_counter()
            if side == "serial":
                serial = reproduce(n_trials, seed=0, map_fn=serial_map)
                t_serial.append(time.perf_counter() - t)
                cpu_serial.append(sum(r.cpu_seconds for r in seen))
            else:
                par = reproduce(n_trials, seed=0, map_fn=map_on(client))
                t_warm.append(time.perf_counter() - t)
                cpu_warm.append(sum(r.cpu_seconds for r in seen))
            per = _cpu_per_process(seen)
            if side == "parallel":
                span_warm.append(max(per.values()))
            print(f"  {side:8s} {(t_serial if side == 'serial' else t_warm)[-1]:6.2f} s, task CPU "
                  f"{(cpu_serial if side == 'serial' else cpu_warm)[-1]:.2f} s ("
                  f"{', '.join(f'{w} {c:.2f}' for w, c in sorted(per.items()))}), {load()}")
    ts, tw = min(t_serial), min(t_warm)
    same = json.dumps(_strip(serial), sort_keys=True) == json.dumps(_strip(par), sort_keys=True)
    print(f"  best of each: serial {ts:.2f} s ({ts / (3 * n_trials):.2f} s per trial), {jobs} workers warm "
          f"{tw:.2f} s -> speed-up {ts / tw:.2f}x (median pair {_median(t_serial) / _median(t_warm):.2f}x); "
          f"task CPU serial {min(cpu_serial):.2f} s, workers {min(cpu_warm):.2f} s; cluster start {t_start:.1f} s; "
          f"results identical: {same}; {load()}")
    print(f"  by CPU time (what a loaded machine distorts least): serial {min(cpu_serial):.2f} s against the "
          f"busiest process's {min(span_warm):.2f} s warm -> {min(cpu_serial) / min(span_warm):.2f}x on {jobs} free "
          f"cores; a fresh engine (workers started by the estimate): busiest {cold['span_s']:.2f} s -> "
          f"{min(cpu_serial) / cold['span_s']:.2f}x, workers up after {cold['start_wall_s']:.2f} s of wall")
    return {"n_trials": 3 * n_trials, "serial_s": t_serial, "warm_s": t_warm, "cpu_serial_s": cpu_serial,
            "cpu_span_warm_s": span_warm, "cold": cold,
            "cpu_workers_s": cpu_warm, "cluster_start_s": t_start, "speedup_warm_best": ts / tw,
            "speedup_warm_median": _median(t_serial) / _median(t_warm), "identical": same, "jobs": jobs,
            "load_after": os.getloadavg()}


def _cpu_per_process(results) -> dict[str, float]:
    """Task CPU seconds per process (this one: ``local``; a worker: ``pool:PID``)."""
    out: dict[str, float] = {}
    for r in results:
        key = "local" if r.worker.startswith("local") else r.worker
        out[key] = out.get(key, 0.0) + r.cpu_seconds
    return out


def _cold_reproduce(jobs: int, n_trials: int, seen: list) -> dict:
    """``reproduce()`` on a fresh engine (the default start cost: workers only once the estimate says so):
    this process's whole CPU (its tasks, the estimate, the feeder) against each worker's task CPU; the
    busiest process bounds the run on free cores. ``start_wall_s``: from the first task to the workers'
    first result, less that task's own time."""
    from rig.analysis.reproduce import reproduce
    from rig.catalog.batch import Engine as _E

    eng = _E(jobs)
    seen.clear()

    def _m(fn, items, cost=None):
        res = eng.run(fn, items, cost=cost, progress=lambda d, t, r: stamps.append((time.perf_counter(), r)))
        seen.extend(res)
        return [r.value for r in res]

    stamps: list = []
    t0, c0 = time.perf_counter(), time.process_time()
    reproduce(n_trials, seed=0, map_fn=_m)
    wall, own = time.perf_counter() - t0, time.process_time() - c0
    eng.close()
    per = _cpu_per_process(seen)
    per["local"] = own
    first = next(((t - t0) - r.seconds for t, r in stamps if r.worker.startswith("pool")), float("nan"))
    print(f"  fresh engine: {wall:.2f} s wall; CPU {', '.join(f'{w} {c:.2f}' for w, c in sorted(per.items()))}; "
          f"{eng.local_tasks} of {len(seen)} tasks here; estimate {eng.estimate_s or 0:.1f} s; {load()}")
    return {"wall_s": wall, "cpu_s": per, "span_s": max(per.values()), "start_wall_s": first,
            "local_tasks": eng.local_tasks, "estimate_s": eng.estimate_s}


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def _rig() -> list[str]:
    exe = Path(sys.executable).parent / "rig"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "rig.cli"]


def _timed(cmd: list[str]) -> tuple[float, float, str]:
    """Wall time, CPU time of the command and the children it reaps (user + system), output.
    Workers forked by a forkserver (the engine's default start) are the forkserver's children,
    and the forkserver is not reaped by the command: their CPU is missing from the figure;
    ``RIG_BATCH_START_METHOD=spawn`` makes it complete."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "COLUMNS": "200"})
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), p.stdout


def bench_cli(jobs: int, n_files: int, n_trials: int, rounds: int = 2) -> dict:
    """The commands end to end, fresh processes: --jobs 1 against --jobs N, interleaved."""
    print(f"cli: fresh `rig` processes, --jobs 1 (serial, no Dask) against --jobs {jobs}, worker start "
          f"{os.environ.get('RIG_BATCH_START_METHOD', 'forkserver')}, {autogroup()}, {load()}")
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        files_dir = d / "files"
        files_dir.mkdir()
        _mk_files(n_files, files_dir)
        cases = {
            "reproduce": lambda j, k: _rig() + ["reproduce", "--trials", str(n_trials), "--jobs", str(j),
                                                "--json", str(d / f"rep-{j}-{k}.json")],
            "identify": lambda j, k: _rig() + ["identify", str(files_dir), "--jobs", str(j),
                                               "--db", str(d / f"cat-{j}-{k}.duckdb")],
        }
        _timed(_rig() + ["reproduce", "--trials", "2", "--jobs", "1", "--lubricant", "dry"])  # numba cache, page cache
        for name, cmd in cases.items():
            walls: dict[int, list] = {1: [], jobs: []}
            cpus: dict[int, list] = {1: [], jobs: []}
            for k in range(2 * rounds):
                j = 1 if k % 4 in (0, 3) else jobs
                la = os.getloadavg()[0]
                w, c, _ = _timed(cmd(j, k))
                walls[j].append(w)
                cpus[j].append(c)
                print(f"  {name:9s} --jobs {j}: {w:6.2f} s wall, {c:6.2f} s CPU (reaped processes), "
                      f"load before {la:.2f}")
            if name == "reproduce":
                reps = [json.loads(p.read_text()) for p in sorted(d.glob("rep-*.json"))]
                same = len({json.dumps(_strip(r), sort_keys=True) for r in reps}) == 1
            else:
                import duckdb

                rows = set()
                for p in sorted(d.glob("cat-*.duckdb")):
                    with duckdb.connect(str(p), read_only=True) as con:
                        rows.add(json.dumps(con.execute("SELECT path, ok, A_mu, B_mu, L_um FROM identify_results "
                                                        "ORDER BY path").fetchall()))
                same = len(rows) == 1
            s1, sn = min(walls[1]), min(walls[jobs])
            print(f"  {name}: best serial {s1:.2f} s, best --jobs {jobs} {sn:.2f} s -> speed-up {s1 / sn:.2f}x "
                  f"(median pair {_median(walls[1]) / _median(walls[jobs]):.2f}x); results identical: {same}; "
                  f"{load()}")
            out[name] = {"wall_s": {str(k): v for k, v in walls.items()}, "cpu_s": {str(k): v for k, v in cpus.items()},
                         "speedup_best": s1 / sn, "speedup_median": _median(walls[1]) / _median(walls[jobs]),
                         "identical": same, "load_after": os.getloadavg()}
    return out


def bench_overhead(jobs: int, n: int = 2000) -> dict:
    """Round trip per task, no-op tasks, warm: the engine's own workers (what `rig` uses without
    --scheduler) against a Dask LocalCluster of as many workers (what it used before)."""
    out = {}
    for name, ctx in (("own workers", _warm_engine(jobs)), ("Dask LocalCluster", dask_client(jobs))):
        with ctx as client:
            run_tasks(_noop, list(range(10)), client=client)
            t0 = time.perf_counter()
            run_tasks(_noop, list(range(n)), client=client)
            dt = time.perf_counter() - t0
            if isinstance(client, Engine) and client._pool is not None:  # the workers' own round trip
                t1 = time.perf_counter()
                for f in [client._pool.executor.submit(_noop, i) for i in range(n)]:
                    f.result()
                rt = (time.perf_counter() - t1) / n * 1e3
                print(f"overhead, a forked worker's round trip alone: {rt:.3f} ms per task, {load()}")
        print(f"overhead, {name}: {n} no-op tasks, {jobs} processes: {dt:.2f} s = {dt / n * 1e3:.3f} ms per task "
              f"(submit, run, gather, in order), {load()}")
        out[name] = {"n": n, "seconds": dt, "per_task_ms": dt / n * 1e3, "jobs": jobs, "load_after": os.getloadavg()}
    return out


#: `rig reproduce` batches from 1 s to about 30 s of serial work (0.3-0.6 s per trial at rest)
SIZES = (("2 trials", ["--trials", "2", "--lubricant", "boundary"]),
         ("4 trials", ["--trials", "4", "--lubricant", "boundary"]),
         ("8 trials", ["--trials", "8", "--lubricant", "dry"]),
         ("24 trials", ["--trials", "8"]),
         ("72 trials", ["--trials", "24"]))


def bench_sizes(jobs: int, rounds: int = 3) -> dict:
    """`rig reproduce` as a user runs it (fresh processes, start-up included) at every batch size,
    --jobs 1 against --jobs N, interleaved (1, N, N, 1, ...): the target is --jobs N never more than
    5 % slower at any size, and at least 1.6x on 2 cores for a batch of 30 s or more."""
    print(f"sizes: fresh `rig reproduce` processes, --jobs 1 against --jobs {jobs}, min and median of "
          f"{rounds} each, {autogroup()}, {load()}")
    _timed(_rig() + ["reproduce", "--trials", "2", "--jobs", "1", "--lubricant", "dry"])  # numba cache, page cache
    out = {}
    for name, args in SIZES:
        walls: dict[int, list] = {1: [], jobs: []}
        loads = []
        for k in range(2 * rounds):
            j = 1 if k % 4 in (0, 3) else jobs
            loads.append(os.getloadavg()[0])
            w, _, _ = _timed(_rig() + ["reproduce", *args, "--jobs", str(j)])
            walls[j].append(w)
        s1, sn = min(walls[1]), min(walls[jobs])
        print(f"  {name:9s}: --jobs 1 {s1:6.2f} s (median {_median(walls[1]):6.2f}), --jobs {jobs} {sn:6.2f} s "
              f"(median {_median(walls[jobs]):6.2f}) -> {s1 / sn:.2f}x best, {_median(walls[1]) / _median(walls[jobs]):.2f}x "
              f"median; load {min(loads):.2f}-{max(loads):.2f}")
        out[name] = {"wall_s": {str(k): v for k, v in walls.items()}, "speedup_best": s1 / sn,
                     "speedup_median": _median(walls[1]) / _median(walls[jobs]), "load_1min": loads}
    return out


def bench_catalog(n_files: int) -> dict:
    """The catalogue's own costs: reading new files, the unchanged-file check, writing results."""
    from rig.catalog import build
    from rig.catalog.batch import TaskResult
    from rig.catalog.build import record_identify

    with tempfile.TemporaryDirectory() as d:
        files = _mk_files(min(n_files, 20), Path(d))
        t0 = time.perf_counter()
        build(d)
        t_new = (time.perf_counter() - t0) / len(files)
        t0 = time.perf_counter()
        for _ in range(5):
            build(d)
        t_same = (time.perf_counter() - t0) / 5 / len(files)
        from rig.catalog.tasks import identify_file

        r = run_tasks(identify_file, [(str(files[0]), {})], jobs=1)[0]
        n = 2000
        fake = [TaskResult((f"/archive/f{i:06d}.csv", {}), True, r.value, None, 0.5) for i in range(n)]
        t0 = time.perf_counter()
        record_identify(Path(d) / "catalog.duckdb", fake, {})
        t_write = (time.perf_counter() - t0) / n
        report_kb = len(json.dumps(r.value["report"])) / 1e3
        db_mb = (Path(d) / "catalog.duckdb").stat().st_size / 1e6
    print(f"catalog: index a new file {t_new * 1e3:.0f} ms, check an unchanged one {t_same * 1e6:.0f} µs, "
          f"write an identify result {t_write * 1e3:.2f} ms ({report_kb:.1f} kB JSON report); "
          f"catalogue of {n} results {db_mb:.1f} MB, {load()}")
    return {"index_new_s": t_new, "check_unchanged_s": t_same, "write_result_s": t_write,
            "report_kB": report_kb, "db_MB_per_2000": db_mb, "load_after": os.getloadavg()}


def main(argv: list[str]) -> None:
    args = list(argv)

    def opt(name, default):
        if name in args:
            i = args.index(name)
            v = args[i + 1]
            del args[i:i + 2]
            return v
        return default

    jobs = int(opt("--jobs", 2))
    n_files = int(opt("--files", 50))
    n_trials = int(opt("--trials", 8))
    rounds = int(opt("--rounds", 2))
    out = opt("--json", None)
    what = args or ["overhead", "identify", "reproduce", "catalog", "cli"]
    print(f"bench_batch: {os.cpu_count()} cores, {jobs} workers, {autogroup()}, {load()}")
    res = {}
    for w in what:
        if w == "identify":
            res[w] = bench_identify(jobs, n_files)
        elif w == "reproduce":
            res[w] = bench_reproduce(jobs, n_trials, rounds)
        elif w == "cli":
            res[w] = bench_cli(jobs, n_files, n_trials, rounds)
        elif w == "sizes":
            res[w] = bench_sizes(jobs, rounds)
        elif w == "overhead":
            res[w] = bench_overhead(jobs)
        elif w == "catalog":
            res[w] = bench_catalog(n_files)
        else:
            sys.exit(f"unknown benchmark {w!r}: identify | reproduce | overhead | catalog | cli | sizes")
    if out:
        Path(out).write_text(json.dumps(res, indent=2) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
