"""The simulated rig: plant (rig.sim.plant) + controller (rig.control) in a numba closed loop.

    rig = SimRig(profile, "boundary", seed=0)        # or a FrictionModel
    for block in rig.run_blocks(x_ref_um, block_ticks=100):
        ...  # dict of numpy arrays, one entry per loop tick (keys: BLOCK_KEYS)

    rig.reset(x0_um)                                 # per-tick plant API for the emulators
    reading = rig.plant_step(valve_cmd)              # advance one tick, then sample sensors

Repeatable bit for bit for a seed: the sensor noise comes from a numpy PCG64 stream
drawn in fixed pages of 4 x 65536 normals, whatever the block size, so the same seed
and the same calls give the same numbers.

Start of a run (``run_blocks`` with ``reset=True``): the test piece is at rest at
``x_ref[0]`` with no force in the chain, and the friction state at steady state for the
reference's mean speed over the first 0.1 s, or for ``sim.initial_creep_um_s`` when the
reference starts with a hold (slower than that creep).

Friction-model extensions applied here (the sensor/fixture side, diagnosis.md):
``sensor_lag`` (first-order lag tau_s on the friction channel, before the load cell's
100 Hz filter), ``force_offset_drift`` (rate_N_per_s * t added to the measured
friction), ``normal_force_variation`` (friction is always mu (N1 + N2), and the normal
forces always vary), ``finite_stiffness`` (the compliance between the LVDT point and the
interface, in place of the profile's fixture compliance: rig.model.loading), ``time_delay`` (steady_state baseline: |mu| = mu_ss of the slip velocity
delay_s ago, from a ring buffer, the direction that of the current velocity; such a
memoryless law, like one with a negative slope, is ill posed on a massless interface,
so these models get the interface mass ``sim.interface_mass_kg``, see docs/sim.md). The friction-law extensions
(second state, aging, wear, position-periodic) are in rig.model.friction's kernels.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Iterator

import numpy as np

from rig.control import apply_switches, controller_params_from_profile, new_controller_state
from rig.model.feedforward import (friction_feedforward_for_plan, friction_feedforward_N,  # noqa: F401
                                   feedforward_model, initial_velocity_um_s)
from rig.model.friction import N_STATE, init_state
from rig.model.loading import lvdt_to_interface_compliance_um_per_N
from rig.model.sensors import cutoff_tau_s, lowpass_coefficients, prefilter_noise_gain
from rig.model.spec import FrictionModel
from rig.sim import plant as pl
from rig.config.profile import RigProfile, default_profile_path, load_profile

BLOCK_KEYS = pl.BLOCK_KEYS
NOISE_PAGE_TICKS = 65536


def build_plant_params(profile: RigProfile, model: FrictionModel, normal_force_N: float | None = None) -> np.ndarray:
    """Pack the profile (and the model's sensor/fixture extensions) for the numba plant."""
    q = np.zeros(pl.N_QPAR)
    _pack_hydraulics(q, profile, model)
    _pack_normal(q, profile, normal_force_N)
    q[pl.Q_XORG] = profile.stroke.home_um
    _pack_sensors(q, profile, model)
    _pack_interface(q, profile, model)
    return q


def _pack_hydraulics(q: np.ndarray, profile: RigProfile, model: FrictionModel) -> None:
    """Time steps, servovalve, actuator, fixture compliances and the inverse of the trapezoidal step's
    matrix of (pressure force, velocity, spring force) (docs/sim.md)."""
    dt = profile.dt_s
    nsub = profile.sim.substeps
    h = dt / nsub
    act = profile.actuator
    q[pl.Q_H] = h
    q[pl.Q_NSUB] = nsub
    q[pl.Q_DT] = dt
    q[pl.Q_AV] = math.exp(-h / profile.servovalve.time_constant_s)
    q[pl.Q_STIC] = profile.servovalve.stiction_band_cmd
    q[pl.Q_FFS] = act.full_scale_force_N
    q[pl.Q_TAUL] = act.leakage_time_constant_s
    q[pl.Q_KH] = act.hydraulic_stiffness_N_per_um
    q[pl.Q_MKG] = act.moving_mass_kg
    q[pl.Q_CA] = act.viscous_damping_N_s_per_um
    c_tp = 1.0 / profile.fixture.test_piece_stiffness_N_per_um
    # LVDT point -> interface: the fixture's compliance, or the model's finite_stiffness instead
    c_li = lvdt_to_interface_compliance_um_per_N(1.0 / profile.fixture.fixture_stiffness_N_per_um,
                                                 model.stiffness_N_per_um)
    km = 1.0 / (c_tp + c_li)
    q[pl.Q_CTP] = c_tp
    q[pl.Q_CLI] = c_li
    q[pl.Q_KM] = km
    tau = act.leakage_time_constant_s
    kh = act.hydraulic_stiffness_N_per_um
    g = h * 1e6 / act.moving_mass_kg
    ca = act.viscous_damping_N_s_per_um
    K = np.array([
        [1.0 + 0.5 * h / tau, 0.5 * h * kh, 0.0],
        [-0.5 * g, 1.0 + 0.5 * g * ca, 0.5 * g],
        [0.0, -0.5 * h * km, 1.0],
    ])
    Kinv = np.linalg.inv(K)
    q[pl.Q_K:pl.Q_K + 9] = Kinv.ravel()
    q[pl.Q_QV:pl.Q_QV + 3] = Kinv[:, 2] * (-h * km)


def _pack_normal(q: np.ndarray, profile: RigProfile, normal_force_N: float | None) -> None:
    """The riders' normal forces (N): nominal (the trial's, else the profile's), offsets, springs, faces."""
    nm = profile.normal
    n_nom = nm.nominal_force_N if normal_force_N is None else float(normal_force_N)
    q[pl.Q_N10] = n_nom * (1.0 + nm.rider_offset_fraction[0])
    q[pl.Q_N20] = n_nom * (1.0 + nm.rider_offset_fraction[1])
    q[pl.Q_KR] = nm.rider_spring_stiffness_N_per_um
    q[pl.Q_TAP1], q[pl.Q_TAP2] = nm.face_taper_um_per_mm
    q[pl.Q_WA1], q[pl.Q_WA2] = nm.face_waviness_amplitude_um
    q[pl.Q_WL1], q[pl.Q_WL2] = nm.face_waviness_wavelength_um
    q[pl.Q_WP1], q[pl.Q_WP2] = nm.face_waviness_phase_rad


def _pack_sensors(q: np.ndarray, profile: RigProfile, model: FrictionModel) -> None:
    """The LVDT's and the load cells' chains, and the model's sensor_lag and force_offset_drift."""
    dt = profile.dt_s
    s = profile.sensors
    q[pl.Q_LV_Q] = s.lvdt.quantization_um
    q[pl.Q_LV_MIN] = s.lvdt.min_um
    q[pl.Q_LV_MAX] = s.lvdt.max_um
    # noise enters before each analog filter; its input per tick gives the reading the
    # profile's sigma (rig.model.sensors.prefilter_noise_gain)
    for ia, ig, isig, fc, sig in ((pl.Q_LV_A, pl.Q_LV_G, pl.Q_LV_SIG, s.lvdt.cutoff_hz, s.lvdt.noise_sigma_um),
                                  (pl.Q_FL_A, pl.Q_FL_G, pl.Q_FL_SIG, s.friction_load_cell.cutoff_hz,
                                   s.friction_load_cell.noise_sigma_N),
                                  (pl.Q_NL_A, pl.Q_NL_G, pl.Q_NL_SIG, s.normal_load_cells.cutoff_hz,
                                   s.normal_load_cells.noise_sigma_N)):
        tau_f = cutoff_tau_s(fc)
        q[ia], q[ig] = lowpass_coefficients(dt, tau_f)
        q[isig] = sig * (1.0 - q[ia]) * prefilter_noise_gain(dt, tau_f)
    if "sensor_lag" in model.extensions:
        tau_s = model.get("tau_s", 0.0)
        if tau_s < 0:
            raise ValueError("sensor_lag needs tau_s >= 0")
        q[pl.Q_SL_ON] = 1.0
        q[pl.Q_SL_A], q[pl.Q_SL_G] = lowpass_coefficients(dt, tau_s)
    if "force_offset_drift" in model.extensions:
        q[pl.Q_DRIFT] = model.get("rate_N_per_s", 0.0)


def _pack_interface(q: np.ndarray, profile: RigProfile, model: FrictionModel) -> None:
    """A memoryless (steady_state) model with a delay or a negative slope needs inertia at the
    interface (eq. 9 of Hess & Soom has it); a positive slope alone is well posed massless."""
    dt = profile.dt_s
    steady = not model.has_state
    delayed = "time_delay" in model.extensions
    if delayed and not steady:
        warnings.warn("time_delay applies to a steady_state baseline only (diagnosis.md); ignored for rate_state",
                      stacklevel=4)
        delayed = False
    use_mass = steady and (delayed or model.get("c_mu") <= 0.0)
    q[pl.Q_STEADY] = 1.0 if use_mass else 0.0
    q[pl.Q_DELAY] = max(1, int(round(model.get("delay_s", 0.0) / dt))) if delayed else 0
    q[pl.Q_MIH] = profile.sim.interface_mass_kg * 1e-6 / (dt / profile.sim.substeps)


class SimRig:
    """Simulated servohydraulic double-shear friction rig (plant + controller).

    ``profile``: a :class:`RigProfile` or a path to one (None: config/rigs/sim.yaml);
    ``friction_model``: a :class:`FrictionModel` or a lubricant name of the profile;
    ``normal_force_N``: nominal per-rider normal force (default: the profile's);
    ``seed``: seed of the sensor-noise stream.
    """

    def __init__(self, profile: RigProfile | str | Path | None = None,
                 friction_model: FrictionModel | str = "boundary", normal_force_N: float | None = None,
                 seed: int = 0):
        if profile is None:
            profile = default_profile_path()
        if not isinstance(profile, RigProfile):
            profile = load_profile(profile)
        if isinstance(friction_model, str):
            friction_model = profile.friction_model(friction_model)
        self.profile = profile
        self.friction_model = friction_model
        self.seed = seed
        self.dt_s = profile.dt_s
        self.rate_hz = profile.loop.rate_hz
        self.normal_force_N = profile.normal.nominal_force_N if normal_force_N is None else float(normal_force_N)
        if not (math.isfinite(self.normal_force_N) and self.normal_force_N > 0):
            raise ValueError(f"normal_force_N must be positive and finite, got {normal_force_N!r}")
        self.q = build_plant_params(profile, friction_model, normal_force_N)
        self.fp = friction_model.to_array()
        self.c = controller_params_from_profile(profile)
        self.cs = new_controller_state()
        self.ff_model: FrictionModel | None = None   # friction feed-forward's model (None: feedforward_model)
        self.ff_N = np.empty(0)                       # the last run's feed-forward track (N per tick)
        self.st = np.zeros(pl.N_ZSTATE)
        self.fs = np.zeros(N_STATE)
        self.ring = np.zeros(max(1, int(self.q[pl.Q_DELAY])))  # slip velocity of the last `delay` ticks
        self._rng = np.random.Generator(np.random.PCG64(seed))
        self._page = np.zeros((0, 4))
        self._cursor = 0
        self.reset(profile.stroke.home_um)

    # ------------------------------------------------------------------ state
    @property
    def time_s(self) -> float:
        return float(self.st[pl.Z_TICK] * self.dt_s)

    def reset(self, x0_um: float | None = None, v_init_um_s: float | None = None) -> None:
        """Put the test piece at rest at ``x0_um`` (LVDT point), no force in the chain, the
        friction state at steady state for ``v_init_um_s`` (default: the profile's
        ``sim.initial_creep_um_s``), controller and filters reset, time 0. The noise stream
        continues (a fresh SimRig with the same seed repeats everything)."""
        if x0_um is None:
            x0_um = self.profile.stroke.home_um
        v_init = self.profile.sim.initial_creep_um_s if v_init_um_s is None else max(abs(v_init_um_s), 1e-12)
        st = self.st
        st[:] = 0.0
        st[pl.Z_XA] = x0_um
        st[pl.Z_XT] = x0_um
        st[pl.Z_X0] = x0_um
        st[pl.Z_LVF] = x0_um
        n1, n2 = pl.normal_forces(self.q, float(x0_um))
        st[pl.Z_N1] = n1
        st[pl.Z_N2] = n2
        st[pl.Z_N1F] = n1
        st[pl.Z_N2F] = n2
        self.fs[:] = 0.0
        init_state(self.fp, self.fs, v_init)
        self.ring[:] = v_init
        self.cs[:] = new_controller_state()

    # ------------------------------------------------------------------ noise
    def _noise(self, n_needed: int) -> tuple[np.ndarray, int, int]:
        """(page, start, count) with count <= n_needed, from the fixed-page noise stream."""
        if self._cursor >= self._page.shape[0]:
            self._page = self._rng.standard_normal((NOISE_PAGE_TICKS, 4))
            self._cursor = 0
        count = min(n_needed, self._page.shape[0] - self._cursor)
        start = self._cursor
        self._cursor += count
        return self._page, start, count

    # ------------------------------------------------------------------ closed loop
    def run_blocks(self, x_ref_um, block_ticks: int = 100, reset: bool = True,
                   chunk_ticks: int = 20000, controller: dict | None = None,
                   ff_N: np.ndarray | None = None) -> Iterator[dict]:
        """Run the closed loop over the reference (µm, one value per tick); yield block dicts.

        Each block is a dict of numpy arrays (keys BLOCK_KEYS) covering ``block_ticks`` ticks
        (the last may be shorter). With ``reset`` (default), the run starts at rest at
        ``x_ref[0]`` (see the module docstring). The reference is checked here, before any
        block is produced (ValueError).

        ``controller``: the recipe's feed-forward switches for this run (a compiled plan's
        ``controller``, rig.config.recipe.ControllerSwitches): ``ff1`` False sets the
        profile's FF1 gain to 0; ``friction_ff`` True feeds :func:`friction_feedforward_N` of
        :attr:`ff_model` (default: :func:`feedforward_model` of the simulated friction model:
        its single-state law, exact for the profile's lubricants) at the nominal 2 N. None: the profile's FF1, no friction feed-forward.
        ``ff_N``: the friction feed-forward per tick as given (a paused plan's pieces: the plan's, held
        through the pause), instead of computing it along this reference."""
        xref = np.ascontiguousarray(x_ref_um, dtype=np.float64)
        if xref.ndim != 1 or xref.size == 0:
            raise ValueError("x_ref_um must be a non-empty 1-D array")
        if not np.all(np.isfinite(xref)):
            raise ValueError("x_ref_um contains NaN or infinite values")
        if block_ticks < 1:
            raise ValueError("block_ticks must be >= 1")
        lv = self.profile.sensors.lvdt
        lo, hi = float(xref.min()), float(xref.max())
        if lo < lv.min_um or hi > lv.max_um:
            raise ValueError(f"x_ref_um spans {lo:g}..{hi:g} µm, outside the LVDT range "
                             f"{lv.min_um:g}..{lv.max_um:g} µm of profile '{self.profile.name}'")
        self.c = apply_switches(controller_params_from_profile(self.profile), controller)
        v_init = initial_velocity_um_s(xref, self.rate_hz, self.profile.sim.initial_creep_um_s)
        if ff_N is not None:
            ff = np.ascontiguousarray(ff_N, dtype=np.float64)
        elif self.ff_model is not None and (controller or {}).get("friction_ff", False):
            ff = friction_feedforward_N(xref, self.dt_s, self.ff_model, 2.0 * self.normal_force_N, v_init)
        else:
            ff = friction_feedforward_for_plan(controller, xref, self.dt_s, self.friction_model,
                                               2.0 * self.normal_force_N, v_init)
        self.ff_N = ff
        return self._blocks(xref, ff, block_ticks, reset, chunk_ticks, v_init)

    def _blocks(self, xref: np.ndarray, ff: np.ndarray, block_ticks: int, reset: bool, chunk_ticks: int,
                v_init: float) -> Iterator[dict]:
        n = xref.size
        if reset:
            self.reset(float(xref[0]), v_init)
        chunk = max(block_ticks, (max(chunk_ticks, block_ticks) // block_ticks) * block_ticks)
        i = 0
        while i < n:
            m = min(chunk, n - i)
            out = np.empty((pl.N_OUT, m))
            k = 0
            while k < m:
                page, j0, cnt = self._noise(m - k)
                pl.run_closed_loop(self.q, self.fp, self.fs, self.st, self.ring, self.c, self.cs, xref, ff, i + k,
                                   page, j0, out, k, cnt)
                k += cnt
            for b in range(0, m, block_ticks):
                e = min(b + block_ticks, m)
                yield {key: out[r, b:e] for r, key in enumerate(BLOCK_KEYS)}
            i += m

    def run(self, x_ref_um, **kw) -> dict:
        """Closed loop over the whole reference; one dict of full-length arrays."""
        blocks = list(self.run_blocks(x_ref_um, block_ticks=kw.pop("block_ticks", 20000), **kw))
        return {key: np.concatenate([b[key] for b in blocks]) for key in BLOCK_KEYS}

    # ------------------------------------------------------------------ per-tick plant API
    def sample(self) -> dict:
        """Sensor readings now (consumes one tick of noise) plus truth; does not advance."""
        page, j, _ = self._noise(1)
        x, f, n1, n2 = pl.plant_sample(self.q, self.st, page[j, 0], page[j, 1], page[j, 2], page[j, 3])
        st = self.st
        return {"t_s": self.time_s, "position_um": x, "friction_N": f, "normal_1_N": n1, "normal_2_N": n2,
                "true_position_um": float(st[pl.Z_XT]), "true_velocity_um_s": float(st[pl.Z_VS]),
                "true_mu": float(st[pl.Z_MU]), "true_friction_N": float(st[pl.Z_FS]),
                "true_normal_1_N": float(st[pl.Z_N1]), "true_normal_2_N": float(st[pl.Z_N2])}

    def plant_step(self, valve_cmd: float) -> dict:
        """Advance the plant one tick with ``valve_cmd`` (clamped to ±1) held, then sample the
        sensors at the new time. Keys: t_s, position_um, friction_N, normal_1_N, normal_2_N,
        valve_cmd, and truth: true_position_um, true_velocity_um_s, true_mu, true_friction_N,
        true_normal_1_N, true_normal_2_N."""
        u = float(valve_cmd)
        if not math.isfinite(u):
            raise ValueError(f"valve_cmd must be finite, got {valve_cmd!r}")
        u = min(1.0, max(-1.0, u))
        pl.plant_advance(self.q, self.fp, self.fs, self.st, self.ring, u)
        d = self.sample()
        d["valve_cmd"] = u
        return d
