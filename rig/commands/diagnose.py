"""``rig diagnose DATA``: what the simulation's friction model gets wrong, why, and the gain of fixing it.

Contract: ../shared/specs/diagnosis.md. Exit status 0 whenever the analysis ran
(whatever it found); a bad input file is one clear error and exit status 1.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("diagnose")
    def diagnose_cmd(
        data: Path = typer.Argument(..., help="Measured trial: .csv (measured-data.md) or .mcap rig log; a "
                                              "directory or a glob runs a batch into the catalogue."),
        baseline: str = typer.Option("rate_state", "--baseline", help="rate_state (default) or steady_state."),
        json_out: Optional[Path] = typer.Option(None, "--json", help="Write the JSON report (rig.diagnosis/1)."),
        plot: Optional[Path] = typer.Option(None, "--plot", help="Write the diagnosis figure (PNG)."),
        model_out: Optional[Path] = typer.Option(None, "--model-out",
                                                 help="Write the extended friction model (YAML) for "
                                                      "`rig run --sim --friction-model`."),
        jobs: Optional[int] = typer.Option(None, "--jobs", help="Batch: N worker processes (default: all cores)."),
        scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Batch: an existing Dask cluster, "
                                                                          "tcp://HOST:PORT."),
        db: Optional[Path] = typer.Option(None, "--db", help="Batch: the catalogue (default DIR/catalog.duckdb)."),
    ):
        """Fit the friction model, find and name what it misses, extend it, measure the gain on hold-out data.

        With a directory or a glob (or --jobs/--scheduler/--db), each file is diagnosed on its own,
        in parallel, and the results go into the catalogue (docs/catalog.md)."""
        from rich.console import Console

        from rig.data import DataFormatError, atomic_write_text
        from rig.log import load_trial

        err = Console(stderr=True)
        if baseline not in ("rate_state", "steady_state"):
            err.print(f"[red]error:[/red] --baseline must be rate_state or steady_state, not {baseline!r}")
            raise typer.Exit(2)
        from rig.commands.catalog import diagnose_summary, is_batch, run_batch

        if is_batch([str(data)], jobs, scheduler, db):
            if json_out or plot or model_out:
                err.print("[red]error:[/red] --json, --plot and --model-out are for single runs; a batch writes "
                          "its results into the catalogue")
                raise typer.Exit(2)
            run_batch("diagnose", [str(data)], {"baseline": baseline}, jobs=jobs, scheduler=scheduler, db=db,
                      summarize=diagnose_summary)
            return
        try:
            trial = load_trial(data)
        except DataFormatError as exc:
            err.print(f"[red]error:[/red] {exc}")
            raise typer.Exit(1)
        except Exception as exc:  # OSError, ValueError, a broken MCAP: one clear error
            err.print(f"[red]error:[/red] {data}: cannot read the trial: {exc}", highlight=False)
            raise typer.Exit(1)
        from rig.diagnosis import diagnose

        try:
            with err.status("diagnosing...") as status:
                d = diagnose(trial, baseline=baseline, progress=lambda m: status.update(f"diagnosing: {m}"))
        except ValueError as exc:
            msg = str(exc)
            err.print(f"[red]error:[/red] {msg if str(data) in msg else f'{data}: {msg}'}", markup=True,
                      highlight=False)
            raise typer.Exit(1)
        rep = d.report()
        rep["data"] = str(data)
        typer.echo(summary(dict(rep, _noise_N=d.grid.noise_N)))
        if json_out is not None:
            atomic_write_text(json_out, json.dumps(rep, indent=2) + "\n")
        if plot is not None:
            from rig.diagnosis.plot import plot_diagnosis

            plot_diagnosis(d, plot)
        if model_out is not None:
            d.model.to_yaml(model_out)


def summary(rep: dict) -> str:
    """A short human summary of a report."""
    b = rep["baseline"]
    lines = [f"{rep['data']}: baseline {b['model']} "
             + ", ".join(f"{k}={v:.4g}" for k, v in b["params"].items())
             + f"; hold-out RMS {b['holdout_rms_N']:.4g} N"]
    if not rep["findings"]:
        noise = rep.get("_noise_N")
        if noise and b["holdout_rms_N"] > 1.2 * noise:
            lines.append(f"  no finding: no catalogue extension passes the hold-out test, though the residual "
                         f"({b['holdout_rms_N']:.3g} N) exceeds the sensor noise ({noise:.3g} N)")
        else:
            lines.append("  no finding: the baseline explains the data to within its noise")
    for f in rep["findings"]:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in f["params"].items())
        lines.append(f"  found {f['cause']} ({ps}): hold-out RMS {f['holdout_rms_N_before']:.4g} -> "
                     f"{f['holdout_rms_N_after']:.4g} N ({f['gain_pct']:+.1f}%, dBIC {f['delta_bic']:.0f})")
        lines.append(f"    {f['evidence']}")
    for u in rep["unexplained"]:
        lines.append(f"  unexplained structure following {u['follows']}: {u['evidence']}")
    m = rep["model"]
    lines.append(f"  model: {m['baseline']}" + (" + " + " + ".join(m["extensions"]) if m["extensions"] else "")
                 + f"; hold-out RMS {rep['holdout_rms_N']:.4g} N")
    return "\n".join(lines)
