"""Byte-identity of the analyses' JSON between two checkouts (issue 23, "Must show").

Runs ``rig identify``, ``stribeck``, ``stability``, ``reproduce`` and ``diagnose`` with ``--json`` on
the same inputs with the code of a base git ref (checked out with ``git worktree add`` in a temporary
directory, kept between runs so its numba cache stays warm) and with this working tree, and prints a
table of command x input: ``same``, ``DIFF`` (JSON bytes or exit status differ) or ``-`` (neither run
wrote JSON: the same refusal, same exit status). Exit 1 on any difference, with a unified diff of the
first; exit 0 when every pair is byte-identical.

Inputs: the shipped recipes' simulated trials (``config/recipes/*.yaml``, made once by this working
tree's ``rig run --sim --seed 0`` into the cache directory and analysed by both checkouts), the shared
real records (``../shared/data/real/*.csv``) and ``tests/data/*.csv``; identify also on two records at once.
``stability`` runs on Table 2
(no input) and on each checkout's own identify report of the velocity-step trial; ``reproduce`` on
2 synthetic trials of the boundary lubricant, with the whole-record fit.

    python benchmarks/compare_json.py --base a731762                  # everything (a few minutes)
    python benchmarks/compare_json.py --base a731762 --commands identify,stribeck,stability,reproduce
    python benchmarks/compare_json.py --base a731762 --inputs velocity-steps,leeman

Both checkouts run with this working tree's ``.venv`` python and their own source first on
``PYTHONPATH``; commands run ``nice -n 10``, ``--jobs`` at a time (default 2).
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_REAL = ROOT.parent / "shared" / "data" / "real"
COMMANDS = ("identify", "stribeck", "stability", "reproduce", "diagnose")
#: the commands that take a record; stability and reproduce have their own inputs (below)
PER_RECORD = ("identify", "stribeck", "diagnose")
#: wall-clock seconds in the reports: masked before the comparison (they differ run to run)
WALL_CLOCK = re.compile(r'("(?:fit_time_s|sim_s)": )[-0-9.eE+]+')
RUN_CLI = "import sys; from rig.cli import app; sys.argv[0] = 'rig'; app()"
#: one process per checkout runs its whole list of commands (the imports, seconds each under load, once)
RUN_MANY = """
import json, sys
from pathlib import Path
from rig.cli import app
out = []
for args, needs in json.loads(sys.argv[1]):
    if needs and not Path(needs).exists():
        out.append(None)
        continue
    try:
        rc = app(args=args, prog_name="rig", standalone_mode=False)
    except SystemExit as exc:
        rc = exc.code
    except BaseException as exc:
        print(f"{args}: {type(exc).__name__}: {exc}", file=sys.stderr)
        rc = -1
    out.append(int(rc or 0))
    sys.stdout.flush()
print("\\n@@RESULTS@@" + json.dumps(out))
"""


def _python() -> str:
    venv = ROOT / ".venv" / "bin" / "python"
    return str(venv) if venv.exists() else sys.executable


def _env(src: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src), "COLUMNS": "200", "NO_COLOR": "1"}
    env.pop("RIG_DEBUG", None)
    return env


def _rig(src: Path, args: list[str], cwd: Path, timeout_s: float = 900.0) -> subprocess.CompletedProcess:
    return subprocess.run(["nice", "-n", "10", _python(), "-c", RUN_CLI, *args], cwd=cwd, env=_env(src),
                          capture_output=True, text=True, timeout=timeout_s)


def base_checkout(ref: str, cache: Path) -> Path:
    """The base ref in a git worktree under ``cache`` (made once per commit, kept for its numba cache)."""
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{ref}^{{commit}}"],
                         capture_output=True, text=True)
    if sha.returncode != 0:
        sys.exit(f"error: --base {ref}: not a commit of {ROOT} ({sha.stderr.strip()})")
    path = cache / f"base-{sha.stdout.strip()[:12]}"
    if not (path / "rig" / "__init__.py").exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "prune"], check=False)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), sha.stdout.strip()],
                       check=True, capture_output=True)
    return path


def make_trials(cache: Path, recipes: list[Path]) -> list[Path]:
    """The recipes' simulated trials, made once (seed 0) by this working tree; reused while they exist."""
    out = []
    for r in recipes:
        dest = cache / "trials" / f"{r.stem}.mcap"
        if not dest.exists():
            dest.parent.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            p = _rig(ROOT, ["run", str(r), "--sim", "--seed", "0", "--out", str(dest)], cwd=ROOT)
            if p.returncode != 0 or not dest.exists():
                print(f"  {r.name}: no trial (exit {p.returncode}): {p.stderr.strip()[-300:]}", file=sys.stderr)
                continue
            print(f"  made {dest.name} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        out.append(dest)
    return out


def jobs_for(commands: list[str], records: list[Path]) -> list[list[tuple[str, str, list[str]]]]:
    """Groups of (command, input label, arguments without --json); a group runs in order in one process
    (stability --params reads the identify report before it, written by the same checkout)."""
    groups = []
    for cmd in commands:
        if cmd in PER_RECORD:
            groups += [[(cmd, p.name, [cmd, str(p)])] for p in records]
    pair = [p for p in records if "sepiolite-velstep" in p.name][:2]
    if "identify" in commands and len(pair) == 2:  # several files: the per-trial and pooled report
        groups.append([("identify", " + ".join(p.name for p in pair), ["identify", *map(str, pair)])])
    steps = [p for p in records if "velocity-steps" in p.name][:1]
    if "identify" in commands and steps:  # both state laws and their comparison
        groups.append([("identify", f"--law both {steps[0].name}", ["identify", "--law", "both", str(steps[0])])])
    if "stability" in commands:
        groups.append([("stability", "Table 2", ["stability"])])
        if "identify" in commands:
            for g in groups:
                cmd, label, _ = g[0]
                if cmd == "identify" and "velocity-steps" in label:
                    g.append(("stability", f"--params identify report of {label}",
                              ["stability", "--params", f"@OUT@/{_name('identify', label)}"]))
    if "reproduce" in commands:
        groups.append([("reproduce", "synth x2 boundary", ["reproduce", "--trials", "2", "--engine", "synth",
                                                           "--lubricant", "boundary", "--whole", "--jobs", "1"])])
    return groups


def _name(cmd: str, label: str) -> str:
    return f"{cmd}--{re.sub(r'[^A-Za-z0-9_.-]+', '_', label)}.json"


def run_side(src: Path, out_dir: Path, jobs: list[tuple[str, str, list[str]]]) -> list[tuple[int | None, str | None]]:
    """Exit status and masked JSON text (None: none written) of each job, in one process of checkout ``src``."""
    todo = []
    for cmd, label, args in jobs:
        args = [a.replace("@OUT@", str(out_dir)) for a in args]
        needs = next((a for a in args if a.startswith(str(out_dir))), None)
        todo.append(([*args, "--json", str(out_dir / _name(cmd, label))], needs))
    p = subprocess.run(["nice", "-n", "10", _python(), "-c", RUN_MANY, json.dumps(todo)], cwd=src, env=_env(src),
                       capture_output=True, text=True, timeout=3600)
    if "@@RESULTS@@" not in p.stdout:
        sys.exit(f"error: {src}: the commands did not finish (exit {p.returncode}): {p.stderr.strip()[-800:]}")
    codes = json.loads(p.stdout.rsplit("@@RESULTS@@", 1)[1])
    out = []
    for (cmd, label, _), rc in zip(jobs, codes):
        f = out_dir / _name(cmd, label)
        out.append((rc, WALL_CLOCK.sub(r"\1<wall clock>", f.read_text(encoding="utf-8")) if f.exists() else None))
    return out


def compare(base: Path, work: Path, groups: list, cache: Path, n_jobs: int) -> list[tuple]:
    """Rows (command, input, same|DIFF|-, detail, base JSON, work JSON), in the order of COMMANDS."""
    srcs = {"base": base, "work": work}
    outs = {side: cache / f"out-{side}" for side in srcs}
    for d in outs.values():
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    n_chunks = max(1, n_jobs // 2)
    chunks = [[j for g in groups[i::n_chunks] for j in g] for i in range(n_chunks)]
    tasks = [(side, chunk) for chunk in chunks if chunk for side in srcs]
    with ThreadPoolExecutor(max_workers=n_jobs) as ex:
        done = list(ex.map(lambda t: run_side(srcs[t[0]], outs[t[0]], t[1]), tasks))
    results = {(side, cmd, label): r for (side, chunk), rs in zip(tasks, done)
               for (cmd, label, _), r in zip(chunk, rs)}
    rows = []
    for key in sorted({k[1:] for k in results}, key=lambda k: (COMMANDS.index(k[0]), k[1])):
        (rb, b), (rw, w) = results[("base", *key)], results[("work", *key)]
        same = rb == rw and b == w
        state = ("same" if b is not None else "-") if same else "DIFF"
        rows.append((*key, state, f"exit {rb}/{rw}", b, w))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="a731762", help="git ref of the base checkout (default a731762)")
    ap.add_argument("--commands", default=",".join(COMMANDS), help="comma-separated subset of " + ", ".join(COMMANDS))
    ap.add_argument("--inputs", default="", help="comma-separated substrings: only the records whose name has one")
    ap.add_argument("--jobs", type=int, default=2, help="commands at a time (default 2)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "rig-compare-json",
                    help="base worktree, trials and outputs (kept between runs)")
    a = ap.parse_args(argv)
    commands = [c.strip() for c in a.commands.split(",") if c.strip()]
    bad = [c for c in commands if c not in COMMANDS]
    if bad or not commands:
        print(f"error: --commands {a.commands}: unknown {', '.join(bad) or '(none given)'}; "
              f"known: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    if a.jobs < 1:
        print(f"error: --jobs must be at least 1 (got {a.jobs})", file=sys.stderr)
        return 2
    a.cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    base = base_checkout(a.base, a.cache)
    records = make_trials(a.cache, sorted((ROOT / "config" / "recipes").glob("*.yaml")))
    records += sorted(SHARED_REAL.glob("*.csv")) + sorted((ROOT / "tests" / "data").glob("*.csv"))
    wanted = [s.strip() for s in a.inputs.split(",") if s.strip()]
    if wanted:
        records = [p for p in records if any(s in p.name for s in wanted)]
    rows = compare(base, ROOT, jobs_for(commands, records), a.cache, a.jobs)
    w = max([len(r[1]) for r in rows] + [5])
    print(f"base {a.base} ({base}) vs working tree {ROOT}")
    print(f"{'command':10} {'input':{w}} {'JSON':5} detail (base/work)")
    for cmd, label, state, detail, _, _ in rows:
        print(f"{cmd:10} {label:{w}} {state:5} {detail}")
    diffs = [r for r in rows if r[2] == "DIFF"]
    print(f"{len(rows)} comparisons, {len(diffs)} differ; {time.perf_counter() - t0:.0f} s wall, "
          f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    if diffs:
        for cmd, label, _, detail, b, w_ in diffs:
            print(f"\n{cmd} {label} ({detail}): the values that differ (path: base -> work, relative change)")
            for line in value_changes(b, w_):
                print("  " + line)
        cmd, label, _, detail, b, w_ = diffs[0]
        print(f"\nfirst difference: {cmd} {label} ({detail})")
        sys.stdout.writelines(difflib.unified_diff((b or "").splitlines(True), (w_ or "").splitlines(True),
                                                   f"base/{cmd}--{label}", f"work/{cmd}--{label}", n=2))
        return 1
    return 0


def _leaves(doc, path: str = ""):
    """(path, value) of every number, string, bool and null of a JSON document."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, f"{path}.{k}" if path else str(k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _leaves(v, f"{path}[{i}]")
    else:
        yield path, doc


def value_changes(base: str | None, work: str | None, limit: int = 40) -> list[str]:
    """The leaves of two JSON texts that differ, with the relative change of a number (and the keys
    only one side has); at most ``limit`` lines. The whole text when either side is not JSON."""
    def parse(text):  # the masked wall clock as a string
        return dict(_leaves(json.loads((text or "null").replace("<wall clock>", '"<wall clock>"'))))

    try:
        b, w = parse(base), parse(work)
    except ValueError:
        return ["(not JSON on one side)"]
    out = []
    for k in list(b) + [k for k in w if k not in b]:
        vb, vw = b.get(k, "<absent>"), w.get(k, "<absent>")
        if vb == vw and (k in b) == (k in w):
            continue
        num = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (vb, vw))
        rel = f", {(vw - vb) / abs(vb):+.2e}" if num and vb else ""
        out.append(f"{k}: {vb!r} -> {vw!r}{rel}")
    return out[:limit] + ([f"... {len(out) - limit} more"] if len(out) > limit else [])


if __name__ == "__main__":
    sys.exit(main())
