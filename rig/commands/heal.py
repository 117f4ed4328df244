"""``rig heal``: frictional healing from the holds of a record (:mod:`rig.analysis.healing`)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from rig.commands.analysis import _con, _fail, _load, _named, _outputs
from rig.commands.common import JSON_HELP, emit_outputs


class HealRate(str, Enum):
    r25 = "25"
    raw = "raw"


def _g(v, fmt: str = ".4g") -> str:
    return "-" if v is None else format(v, fmt)


def heal_cmd(
    data: Path = typer.Argument(..., help="A record with holds (.mcap or .csv): a slide_hold_slide trial, or any "
                                          "trial with rests between slides (e.g. velocity steps).",
                                show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help=JSON_HELP + " (rig.heal/1)"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a PNG: the record with the holds, and "
                                                             "delta mu against log hold time."),
    rate: HealRate = typer.Option(HealRate.r25, "--rate", help="Of an .mcap: '25' the 25 Hz channel, 'raw' "
                                                               "every loop sample."),
    min_hold_s: float = typer.Option(0.5, "--min-hold-s", help="Shorter rests are not holds."),
):
    """Healing per hold: peak friction rise delta_mu_peak, relaxation delta_mu_relax, and the healing
    rate beta_per_decade (delta_mu_peak per decade of hold time) with its standard error."""
    from rig.analysis.healing import heal, plot_heal

    con = _con(json_out)
    if not min_hold_s > 0:
        _fail(f"--min-hold-s must be positive (got {min_hold_s:g})")
    _outputs(json=json_out, plot=plot)
    if rate == HealRate.raw and data.suffix.lower() == ".mcap":
        from rig.data import DataFormatError
        from rig.log import read_trial

        try:
            trial = read_trial(data, channel="raw")
        except DataFormatError as exc:
            _fail(str(exc))
    else:
        trial = _load([data])[0]
    try:
        rep = heal(trial, min_hold_s=min_hold_s)
    except ValueError as exc:
        _fail(_named(str(exc), [data]))
    tab = Table(title=f"holds of {data} (rests from {rep['rests_from']})")
    for c in ("hold", "t (s)", "hold (s)", "v before / after (µm/s)", "Δμ_peak", "Δμ_relax", "reference"):
        tab.add_column(c, justify="right")
    for h in rep["holds"]:
        th = h.get("hold_s_planned", h["hold_s"])
        tab.add_row(str(h["hold"] + 1), f"{h['t_s']:.2f}", f"{th:.3g}",
                    f"{h['v_before_um_s']:.3g} / {h['v_after_um_s']:.3g}", f"{h['delta_mu_peak']:.3e}",
                    f"{h['delta_mu_relax']:.3e}", h["reference"] + (" (reversal)" if h["reversal"] else ""))
    con.print(tab)
    con.print(f"healing rate beta_per_decade = {_g(rep['beta_per_decade'])} ± {_g(rep['beta_per_decade_sd'], '.2g')} "
              f"(Δμ_peak per decade of hold time, holds {', '.join(str(i + 1) for i in rep['holds_in_rate'])}); "
              f"relaxation {_g(rep['relax_per_decade'])} ± {_g(rep['relax_per_decade_sd'], '.2g')} per decade")
    for note in rep["notes"]:
        con.print(f"[yellow]note:[/yellow] {note}", highlight=False)
    emit_outputs(con, json_out, rep, plot, lambda path: plot_heal(rep, path, trial))


def register(app: typer.Typer) -> None:
    app.command("heal")(heal_cmd)
