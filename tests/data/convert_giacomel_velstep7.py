"""Convert velstep7_BRAVA_expb819_basalt.txt (github.com/pgiacomel/steadystate, commit e7876f4, MIT)
to the measured-data CSV (../shared/specs/measured-data.md), as the shared README converts the
other Giacomel records: normal stress scaled to 100 N per rider at its median, friction_N =
friction coefficient x (normal_1_N + normal_2_N), Displ taken as the load-point displacement.

    python tests/data/convert_giacomel_velstep7.py SOURCE.txt tests/data/giacomel-basalt-velstep7.csv
"""

from __future__ import annotations

import sys

import numpy as np

from rig.data import TrialData, write_csv


def main(src: str, out: str) -> int:
    d = np.loadtxt(src, skiprows=1)
    t, x, mu, sn = d[:, 0], d[:, 1], d[:, 2], d[:, 3]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, x, mu, sn = t[keep], x[keep], mu[keep], sn[keep]
    med = float(np.median(sn))
    n = 100.0 * sn / med
    meta = {
        "position_source": "load_point",
        "normal_force_N": "100",
        "source": "github.com/pgiacomel/steadystate, commit e7876f4d4bf9a71bed5670f600e5648d1356581c "
                  "(\"experimental - short D_{RS}: needs steadystate.m\"; later deleted from main), path "
                  "velstep7_BRAVA_expb819_basalt.txt",
        "licence": "MIT, Copyright (c) 2024 Piercarlo Giacomel (LICENSE, commit 5de7fb8 of the same repository)",
        "original_units": "Time(s) s; Displ(microns) um; Friction dimensionless; Normal_stress(MPa) MPa",
        "conversion": "normal stress scaled to 100 N per rider at its median; friction_N = friction coefficient x "
                      "(normal_1_N + normal_2_N)",
        "mapping": f"time_s = Time - {t[0]:.3f} s; position_um = Displ - {x[0]:.3f} um (the file's only "
                   "displacement column, taken as load-point displacement); normal_1_N = normal_2_N = "
                   "100 N x Normal_stress / median(Normal_stress); no position_ref_um",
        "experiment": "BRAVA apparatus, experiment b819, basalt; the velocity step of Figure 1e of Giacomel et al. "
                      "2021, Tectonophysics (per the commit message)",
        "velocity_step": "load-point velocity up-step about 100 -> 300 um/s at time_s ~2.3 (estimated from Displ "
                         "by this conversion); sampling 1 kHz",
        "normal_stress_median_MPa": f"{med:.6f}",
        "rows": f"{t.size} (source rows {d.shape[0]})",
    }
    tr = TrialData(time_s=t - t[0], position_um=x - x[0], friction_N=mu * 2.0 * n, normal_1_N=n, normal_2_N=n.copy(),
                   metadata=meta, source=out)
    write_csv(tr, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:3]))
