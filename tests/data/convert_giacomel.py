"""Convert the single velocity-step records of github.com/pgiacomel/steadystate (MIT) to the
measured-data CSV (../shared/specs/measured-data.md), as the shared README converts the other
Giacomel records: normal stress scaled to 100 N per rider at its median, friction_N = friction
coefficient x (normal_1_N + normal_2_N), Displ taken as the load-point displacement.

    python tests/data/convert_giacomel.py SOURCE.txt OUT.csv     # SOURCE's name picks its entry below

Sources (`git show COMMIT:PATH` in a clone of the repository):
  velstep7_BRAVA_expb819_basalt.txt   commit e7876f4 -> tests/data/giacomel-basalt-velstep7.csv
  velstep1_TR2_exp013_sepiolite.txt   commit 33d44bc -> tests/data/giacomel-sepiolite-velstep1.csv
  velstep2_TR2_exp013_sepiolite.txt   commit 33d44bc -> tests/data/giacomel-sepiolite-velstep2.csv
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from rig.data import TrialData, write_csv

LICENCE = "MIT, Copyright (c) 2024 Piercarlo Giacomel (LICENSE, commit 5de7fb8 of the same repository)"
TR2 = ("TR2 apparatus, experiment 013, sepiolite gouge (a simulated fault gouge with a large characteristic "
       "slip distance D_RS, per the commit message)")
RECORDS = {
    "velstep7_BRAVA_expb819_basalt.txt": {
        "commit": "e7876f4d4bf9a71bed5670f600e5648d1356581c",
        "commit_note": "\"experimental - short D_{RS}: needs steadystate.m\"; later deleted from main",
        "units": "Time(s) s; Displ(microns) um; Friction dimensionless; Normal_stress(MPa) MPa",
        "experiment": "BRAVA apparatus, experiment b819, basalt; the velocity step of Figure 1e of Giacomel et al. "
                      "2021, Tectonophysics (per the commit message)",
        "velocity_step": "load-point velocity up-step about 100 -> 300 um/s at time_s ~2.3 (estimated from Displ "
                         "by this conversion); sampling 1 kHz",
    },
    "velstep1_TR2_exp013_sepiolite.txt": {
        "commit": "33d44bcd130f68a7b50c9f1ce11feff270c42368",
        "commit_note": "\"Single velocity steps from friction tests (already sliced)\"; later deleted from main",
        "units": "Time(s) s; Displ(microns) um; Friction dimensionless; EffectiveNormalstress(MPa) MPa",
        "experiment": TR2,
        "velocity_step": "load-point velocity up-step about 0.2 -> 2 um/s at time_s ~2210 (estimated from Displ "
                         "by this conversion); sampling irregular, median 0.136 s",
    },
    "velstep2_TR2_exp013_sepiolite.txt": {
        "commit": "33d44bcd130f68a7b50c9f1ce11feff270c42368",
        "commit_note": "\"Single velocity steps from friction tests (already sliced)\"; later deleted from main",
        "units": "Time(s) s; Displ(microns) um; Friction dimensionless; EffectiveNormalstress(MPa) MPa",
        "experiment": TR2,
        "velocity_step": "load-point velocity down-step about 2 -> 0.2 um/s at time_s ~230 (estimated from Displ "
                         "by this conversion), then 2.8 h at 0.2 um/s; sampling irregular, median 0.136 s",
    },
}


def main(src: str, out: str) -> int:
    name = Path(src).name
    if name not in RECORDS:
        print(f"{src}: not one of {', '.join(RECORDS)}", file=sys.stderr)
        return 2
    rec = RECORDS[name]
    d = np.loadtxt(src, skiprows=1)
    t, x, mu, sn = d[:, 0], d[:, 1], d[:, 2], d[:, 3]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, x, mu, sn = t[keep], x[keep], mu[keep], sn[keep]
    med = float(np.median(sn))
    n = 100.0 * sn / med
    meta = {
        "position_source": "load_point",
        "normal_force_N": "100",
        "source": f"github.com/pgiacomel/steadystate, commit {rec['commit']} ({rec['commit_note']}), path {name}",
        "licence": LICENCE,
        "original_units": rec["units"],
        "conversion": "normal stress scaled to 100 N per rider at its median; friction_N = friction coefficient x "
                      "(normal_1_N + normal_2_N)",
        "mapping": f"time_s = Time - {t[0]:.3f} s; position_um = Displ - {x[0]:.3f} um (the file's only "
                   "displacement column, taken as load-point displacement); normal_1_N = normal_2_N = "
                   "100 N x Normal_stress / median(Normal_stress); no position_ref_um",
        "experiment": rec["experiment"],
        "velocity_step": rec["velocity_step"],
        "normal_stress_median_MPa": f"{med:.6f}",
        "rows": f"{t.size} (source rows {d.shape[0]})",
    }
    tr = TrialData(time_s=t - t[0], position_um=x - x[0], friction_N=mu * 2.0 * n, normal_1_N=n, normal_2_N=n.copy(),
                   metadata=meta, source=out)
    write_csv(tr, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:3]))
