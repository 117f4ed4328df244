"""``rig diagnose DATA``: what the simulation's friction model gets wrong, why, and the gain of fixing it.

Contract: ../shared/specs/diagnosis.md. Exit status (:mod:`rig.commands.common`):
0 whenever the analysis ran (whatever it found); 2 a bad input file or option
(one clear error naming the file); 1 an output that cannot be written.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from rig.commands.common import (EXIT_BAD_INPUT, EXIT_FAILED, JSON_HELP, check_output_path, console, err_console,
                                 fail, json_to_stdout, progress_bar, write_json)


class Baseline(str, Enum):
    rate_state = "rate_state"
    steady_state = "steady_state"


def register(app: typer.Typer) -> None:
    @app.command("diagnose")
    def diagnose_cmd(
        data: Path = typer.Argument(..., help="Measured trial: .csv (measured-data.md) or .mcap rig log; a "
                                              "directory or a glob runs a batch into the catalogue.",
                                    show_default=False),
        baseline: Baseline = typer.Option(Baseline.rate_state, "--baseline", help="The model to start from."),
        json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.diagnosis/1)"),
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
        from rig.data import DataFormatError
        from rig.log import load_trial

        baseline = baseline.value
        from rig.commands.catalog import is_batch

        if is_batch([str(data)], jobs, scheduler, db):
            if json_out or plot or model_out:
                fail("--json, --plot and --model-out are for single runs; a batch writes its results into the "
                     "catalogue")
            _batch(data, baseline, jobs, scheduler, db)
            return
        for opt, p, sfx in (("--json", json_out, ()), ("--plot", plot, (".png",)),
                            ("--model-out", model_out, (".yaml", ".yml"))):
            if p is not None:
                check_output_path(p, opt, sfx)
        try:
            trial = load_trial(data)
        except DataFormatError as exc:
            fail(str(exc))
        from rig.diagnosis import diagnose

        try:
            with progress_bar(json_out, "diagnosing", unit="candidate fits") as bar:
                def step(msg: str) -> None:
                    bar.update(description=f"diagnosing: {msg}")
                    bar.advance()

                d = diagnose(trial, baseline=baseline, progress=step)
        except ValueError as exc:
            msg = str(exc)
            fail(msg if str(data) in msg else f"{data}: {msg}", EXIT_BAD_INPUT)
        rep = d.report()
        rep["data"] = str(data)
        rep["warnings"] = diagnosis_warnings(rep) + _calibration_warnings(trial, rep)  # issue 21
        text = summary(dict(rep, _noise_N=d.grid.noise_N, _unnamed=d.unnamed, _kinematics=_floor_set(d, "kinematics_set"),
                            _copies=_floor_set(d, "copies_set"), **_undetermined(d)))
        if json_to_stdout(json_out):
            err_console.print(text, markup=False)
        else:
            typer.echo(text)
        if json_out is not None:
            write_json(rep, json_out)
        # what was written, on the terminal (stderr when the JSON goes to stdout); write_json says its own
        con = err_console if json_to_stdout(json_out) else console
        if plot is not None:
            from rig.diagnosis.plot import plot_diagnosis

            try:
                plot_diagnosis(d, plot, warnings=rep["warnings"])
            except OSError as exc:
                fail(f"cannot write {plot}: {exc.strerror or exc}", EXIT_FAILED)
            con.print(f"wrote {plot}", markup=False)
        if model_out is not None:
            try:
                d.model.to_yaml(model_out)
            except OSError as exc:
                fail(f"cannot write {model_out}: {exc.strerror or exc}", EXIT_FAILED)
            con.print(f"wrote {model_out} (the final model, for `rig run --sim --friction-model`)", markup=False)


def _batch(data: Path, baseline: str, jobs: Optional[int], scheduler: Optional[str], db: Optional[Path]) -> None:
    """``rig diagnose DIR``: each file on its own, in parallel, into the catalogue. The batch runs one
    record per process (``jobs`` of them, default every core): a record's own work (its candidates,
    re-splits, final model) then forks no helpers of its own (rig.diagnosis.parallel.inner_jobs), so
    that the calling process's records do not add two processes to the batch's N on N cores."""
    from rig.commands.catalog import diagnose_summary, run_batch
    from rig.diagnosis.parallel import inner_jobs

    with inner_jobs(jobs):
        run_batch("diagnose", [str(data)], {"baseline": baseline}, jobs=jobs, scheduler=scheduler, db=db,
                  summarize=diagnose_summary)


def _calibration_warnings(trial, rep: dict) -> list[dict]:
    """Forces outside a channel's verified range; the extended model's hold-out gain (N of RMS) below the
    friction channel's stated uncertainty (:func:`rig.data.calibration_warnings`)."""
    from rig.data import calibration_warnings

    base, final = rep["baseline"].get("holdout_rms_N"), rep.get("holdout_rms_N")
    gain = base - final if rep.get("findings") and base is not None and final is not None else None
    return calibration_warnings(trial, {"the findings' hold-out gain": gain} if gain is not None else None)


def diagnosis_warnings(rep: dict) -> list[dict]:
    """Parameters of the baseline and of the final model that hit a fit bound or are not physical
    (:mod:`rig.model.checks`)."""
    from rig.model.checks import check_params

    b = rep["baseline"]
    out = check_params(b["params"], b.get("params_sd"), where=f"baseline {b['model']}")
    m = rep["model"]
    where = "model " + " + ".join([m["baseline"], *m["extensions"]])
    if m["extensions"]:
        # with the standard errors: a value whose error exceeds it is flagged "not determined"
        out += check_params(m["params"], m.get("params_sd"), where=where)
    if not m.get("params_sd"):
        # a fit on a bound (rig.diagnosis.core._undetermined_floor) or a refit on all the data that ran to
        # a bound or failed (rig.diagnosis.core.refit_all): no errors
        out.append({"param": None, "value": None, "kind": "undetermined", "where": where,
                    "message": "no standard errors: its fit (or its refit on all the data) runs to a bound or "
                               "fails, so its values are not determined by this record"})
    return out


def _floor_set(d, key: str) -> list[str] | None:
    """The final model's errors a floor sets (core.uncertainty): ``kinematics_set``, its disagreement
    with identify's fit; ``copies_set``, what a copy with no other physics does to it (core.copies_sd)."""
    return d.final_fit.extra.get(key) if d.final_fit is not None else None


def _undetermined(d) -> dict:
    """The final model's profile intervals over each parameter's domain (rig.diagnosis.intervals), and
    the parameters given their whole searched domain instead, for the summary."""
    ex = d.final_fit.extra if d.final_fit is not None else {}
    return {"_profiled": sorted(ex.get("domain_intervals", {})), "_domain_whole": ex.get("domain_whole", {})}


def _or(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " or " + names[-1]


def summary(rep: dict) -> str:
    """A short human summary of a report."""
    from rig.model.checks import MARK, flagged

    b = rep["baseline"]
    fl = flagged(rep.get("warnings", []), f"baseline {b['model']}")
    lines = [f"{rep['data']}: baseline {b['model']} "
             + ", ".join(f"{k}={v:.4g}" + (f" {MARK}" if k in fl else "") for k, v in b["params"].items())
             + f"; hold-out RMS {b['holdout_rms_N']:.4g} N"]
    if not rep["findings"] and rep.get("_unnamed"):
        lines.append("  no finding that the record supports on most of its splits")
    elif not rep["findings"]:
        noise = rep.get("_noise_N")
        if noise and b["holdout_rms_N"] > 1.2 * noise:
            lines.append(f"  no finding: no catalogue extension passes the hold-out test, though the residual "
                         f"({b['holdout_rms_N']:.3g} N) exceeds the sensor noise ({noise:.3g} N)")
        else:
            lines.append("  no finding: the baseline explains the data to within its noise")
    for f in rep["findings"]:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in f["params"].items())
        st = f" [named on {f['stability']:.0%} of the record's splits]" if "stability" in f else ""
        lines.append(f"  found {f['cause']} ({ps}): hold-out RMS {f['holdout_rms_N_before']:.4g} -> "
                     f"{f['holdout_rms_N_after']:.4g} N ({f['gain_pct']:+.1f}%, dBIC {f['delta_bic']:.0f}){st}")
        lines.append(f"    {f['evidence']}")
        alts = [a["cause"] for a in f.get("alternatives", [])]
        if alts:
            lines.append(f"  this record cannot tell {f['cause']} apart from {_or(alts)}: "
                         f"{'they explain' if len(alts) > 1 else 'it explains'} the held-out data about as well")
    for u in rep.get("_unnamed", []):
        if u.get("why"):
            lines.append(f"  not named: {u['cause']} ({u['gain_pct']:+.1f}%): {u['why']}")
            continue
        lines.append(f"  not named: {u['cause']} ({u['gain_pct']:+.1f}% on the main split, but named on only "
                     f"{u['stability']:.0%} of the record's splits): this record cannot tell it apart from no such "
                     "cause")
    for u in rep["unexplained"]:
        lines.append(f"  unexplained structure following {u['follows']}: {u['evidence']}")
    m = rep["model"]
    fl = flagged(rep.get("warnings", []), "model " + " + ".join([m["baseline"], *m["extensions"]]))
    sd = m.get("params_sd", {})
    lines.append(f"  final model: {m['baseline']}" + (" + " + " + ".join(m["extensions"]) if m["extensions"] else "")
                 + ": " + ", ".join(f"{k}={v:.4g}" + (f" ± {sd[k]:.2g}" if sd.get(k) is not None else "")
                                    + (f" {MARK}" if k in fl else "") for k, v in m["params"].items())
                 + f"; hold-out RMS {rep['holdout_rms_N']:.4g} N")
    whole = rep.get("_domain_whole") or {}
    prof = [k for k in rep.get("_profiled") or [] if k not in whole]
    if prof:
        lines.append("  this record does not determine the final model at one point: the errors (±) of "
                     + (", ".join(prof) + " are the half-widths of their" if whole else "all its parameters are the "
                        "half-widths of their") + " profile-likelihood intervals over their domain (`intervals` in the JSON)")
    iv = m.get("intervals", {})
    for why in dict.fromkeys(whole.values()):
        ks = [k for k, w in whole.items() if w == why and k in iv]
        if ks:
            lines.append("  not determined (" + why + "): " + "; ".join(
                f"{k} anywhere in the whole searched domain [{iv[k][0]:.4g}, {iv[k][1]:.4g}]" for k in ks))
    if rep.get("_kinematics"):
        lines.append(f"  the errors of {', '.join(rep['_kinematics'])} are the final model's disagreement with identify's "
                     "whole-record fit of the same record (its segments' velocities, each run's start and the measured "
                     "normal forces), wider than the fit's own: the two kinematics differ (docs/validation.md, Coverage)")
    if rep.get("_copies"):
        lines.append(f"  the errors of {', '.join(rep['_copies'])} are how far a copy of this record with no other "
                     "physics moves them (a 3 % crop at either end, or the steps' timing within a sampling interval), "
                     "wider than the fit's own: the record's kinematics, not its noise, limit them")
    for w in rep.get("warnings", []):
        lines.append(f"  warning (!): {w['where']}: {w['message']}")
    return "\n".join(lines)
