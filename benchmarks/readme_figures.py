"""The README's figures, measured as a new user meets them: in a fresh clone.

Clones this repository's committed HEAD (``git clone``, so uncommitted changes are not in
it) into a temporary directory with ``../shared`` beside it (a symbolic link to the
checkout's), makes a venv there, installs the package as the README's first command does,
then measures, each with its wall time, the CPU time of the command's processes and the
1-minute load average before and after (``os.getloadavg()``):

* the main job (README command 1: ``rig run`` of the velocity-step recipe on the simulated
  rig, then ``rig identify`` with its figure) cold, first thing in the fresh clone, and warm;
* ``rig --help`` (best of 3);
* ``rig warmup`` with a cold numba cache (the cache files deleted) and warm;
* ``rig stability``'s eq. (8) k_cr for every lubricant (paraffin is the README's figure);
* ``rig diagnose tests/data/giacomel-sepiolite-velstep2.csv`` (its kernels cold: plain
  ``rig warmup`` does not compile them) and again warm.

    python benchmarks/readme_figures.py [--repo DIR] [--keep] [--json OUT.json]

Exit 0 when every command ran, 1 when one failed (its output's tail is printed), 2 on bad
arguments. The machine is shared: read the figures beside their load.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

SEPIOLITE = "tests/data/giacomel-sepiolite-velstep2.csv"
RECIPE = "config/recipes/velocity-steps.yaml"


class Failed(RuntimeError):
    """A measured command failed; the message holds its command line and output's tail."""


def _child_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def timed(cmd: list[str], cwd: Path) -> dict:
    """Run ``cmd`` in ``cwd``: wall s, CPU s of it and its children, load before and after."""
    load0, cpu0, t0 = os.getloadavg()[0], _child_cpu_s(), time.perf_counter()
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    out = {"wall_s": round(wall, 2), "cpu_s": round(_child_cpu_s() - cpu0, 2),
           "load_before": round(load0, 2), "load_after": round(os.getloadavg()[0], 2)}
    if res.returncode != 0:
        tail = "\n".join((res.stdout + res.stderr).strip().splitlines()[-15:])
        raise Failed(f"{' '.join(cmd)} (in {cwd}) exited {res.returncode}:\n{tail}")
    out["stdout"] = res.stdout
    return out


def fresh_clone(repo: Path, tmp: Path) -> Path:
    """A clone of ``repo``'s HEAD in ``tmp/rig`` with ``tmp/shared`` linked to the checkout's
    ``../shared``, a venv and the package installed; returns the clone."""
    dest = tmp / "rig"
    subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", str(repo), str(dest)], check=True)
    shared = repo.parent / "shared"
    if shared.is_dir():
        (tmp / "shared").symlink_to(shared.resolve())
    subprocess.run(["python3", "-m", "venv", ".venv"], cwd=dest, check=True)
    return dest


def clear_numba_cache(clone: Path) -> int:
    """Delete numba's cache files (``*.nbi``, ``*.nbc``) in the clone; returns how many."""
    n = 0
    for pattern in ("*.nbi", "*.nbc"):
        for f in clone.rglob(pattern):
            if ".venv" not in f.parts:
                f.unlink()
                n += 1
    return n


def main_job(clone: Path, rig: str, tag: str) -> dict:
    """README command 1's run and identify (the install is measured apart)."""
    mcap = f"out/velocity-steps-{tag}.mcap"
    run = timed([rig, "run", RECIPE, "--sim", "--out", mcap], clone)
    ident = timed([rig, "identify", mcap, "--json", f"out/identify-{tag}.json",
                   "--plot", f"out/identify-{tag}.png"], clone)
    total = {k: round(run[k] + ident[k], 2) for k in ("wall_s", "cpu_s")}
    return {**total, "load_before": run["load_before"], "load_after": ident["load_after"],
            "run_wall_s": run["wall_s"], "identify_wall_s": ident["wall_s"]}


def stability_eq8(clone: Path, rig: str) -> dict:
    """``rig stability``'s eq. (8) k_cr (kN/m) per lubricant, with the command's time."""
    res = timed([rig, "stability", "--json", "out/stability.json"], clone)
    report = json.loads((clone / "out" / "stability.json").read_text())
    res["k_cr_eq8_kN_per_m"] = {lub: round(a["k_cr_eq8_kN_per_m"], 2) for lub, a in report["analyses"].items()}
    return res


def measure(clone: Path) -> dict:
    """Every figure, in the order a new user meets them (the main job first, on a cold cache)."""
    rig = str(clone / ".venv" / "bin" / "rig")
    pip = str(clone / ".venv" / "bin" / "pip")
    (clone / "out").mkdir(exist_ok=True)
    fig: dict[str, dict] = {}
    fig["install"] = timed([pip, "install", "-q", "-e", "."], clone)
    fig["main job, cold"] = main_job(clone, rig, "cold")
    fig["main job, warm"] = main_job(clone, rig, "warm")
    fig["rig --help"] = min((timed([rig, "--help"], clone) for _ in range(3)), key=lambda r: r["wall_s"])
    cleared = clear_numba_cache(clone)
    fig["rig warmup, cold"] = {**timed([rig, "warmup"], clone), "cache_files_deleted": cleared}
    fig["rig warmup, warm"] = timed([rig, "warmup"], clone)
    fig["rig stability (eq. 8)"] = stability_eq8(clone, rig)
    diag = [rig, "diagnose", SEPIOLITE, "--json", "out/diagnose.json"]
    fig["rig diagnose sepiolite velstep2, cold"] = timed(diag, clone)
    fig["rig diagnose sepiolite velstep2, warm"] = timed(diag, clone)
    for v in fig.values():
        v.pop("stdout", None)
    return fig


def print_table(fig: dict, header: dict) -> None:
    for k, v in header.items():
        print(f"{k}: {v}")
    print(f"{'figure':42s} {'wall s':>8s} {'CPU s':>8s} {'load':>12s}  notes")
    for name, v in fig.items():
        notes = ", ".join(f"{k} {val}" for k, val in v.items()
                          if k not in ("wall_s", "cpu_s", "load_before", "load_after"))
        load = f"{v['load_before']:.2f}-{v['load_after']:.2f}"
        print(f"{name:42s} {v['wall_s']:8.2f} {v['cpu_s']:8.2f} {load:>12s}  {notes}")


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1],
                    help="the checkout to clone (default: this one)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary clone (its path is printed)")
    ap.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = ap.parse_args(argv)
    if not (args.repo / ".git").exists():
        ap.error(f"--repo {args.repo}: not a git checkout")
    if args.json is not None and not args.json.parent.is_dir():
        ap.error(f"--json {args.json}: no such directory {args.json.parent}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    head = subprocess.run(["git", "-C", str(args.repo), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True, check=True).stdout.strip()
    header = {"date (UTC)": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M"), "commit": head,
              "cores": os.cpu_count(), "load average at start": os.getloadavg()}
    tmp = Path(tempfile.mkdtemp(prefix="rig-readme-figures-"))
    try:
        clone = fresh_clone(args.repo, tmp)
        fig = measure(clone)
    except (Failed, subprocess.CalledProcessError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        if args.keep:
            print(f"clone kept: {tmp / 'rig'}", file=sys.stderr)
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    header["load average at end"] = os.getloadavg()
    print_table(fig, header)
    if args.json is not None:
        args.json.write_text(json.dumps({"header": header, "figures": fig}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
