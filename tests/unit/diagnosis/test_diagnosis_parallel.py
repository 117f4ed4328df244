"""The diagnosis's inner parallelism respects an outer batch (rig.diagnosis.parallel): a batch of N
processes on N cores leaves each record one process, so the calling process's records fork no
helpers of their own (issue 20: three processes on two cores before)."""

from __future__ import annotations

import os

import pytest

from rig.diagnosis import parallel


@pytest.fixture(autouse=True)
def _no_env(monkeypatch):
    monkeypatch.delenv("RIG_JOBS", raising=False)


def test_the_cores_a_batch_leaves_each_record():
    assert parallel.inner_workers(1, cores=2) == 2          # alone: both cores
    assert parallel.inner_workers(2, cores=2) == 1          # a batch of two on two cores: none to spare
    assert parallel.inner_workers(3, cores=2) == 1          # never below one
    assert parallel.inner_workers(1, cores=8) == parallel.MAX_WORKERS
    assert parallel.inner_workers(4, cores=8) == 2
    assert parallel.inner_workers(8, cores=8) == 1


def test_rig_jobs_overrides(monkeypatch):
    monkeypatch.setenv("RIG_JOBS", "3")
    assert parallel.inner_workers(2, cores=2) == 3


def test_inside_a_batch_a_record_runs_in_its_own_process(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    assert parallel.inner_workers() == 2
    with parallel.inner_jobs(None) as n:                      # --jobs default: every core
        assert n == 1 and parallel.inner_workers() == 1
        # parallel asked, but the budget is one process: every job runs here, no fork
        assert parallel.fork_map(lambda j: (j, os.getpid()), [1, 2, 3], True) == [(j, os.getpid()) for j in (1, 2, 3)]
    with parallel.inner_jobs(1):                              # --jobs 1: the batch is serial, the record may fork
        assert parallel.inner_workers() == 2
    assert parallel.inner_workers() == 2                      # restored after the batch


def test_the_diagnose_batch_sets_the_budget(monkeypatch, tmp_path):
    """``rig diagnose DIR --jobs 2`` runs its batch with each record's budget at one process."""
    import typer
    from typer.testing import CliRunner

    import rig.commands.catalog as cat
    from rig.commands import diagnose as cmd

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    seen = []
    monkeypatch.setattr(cat, "run_batch", lambda *a, **k: seen.append((k["jobs"], parallel.inner_workers())))
    app = typer.Typer()
    cmd.register(app)
    app.command("noop")(lambda: None)
    res = CliRunner().invoke(app, ["diagnose", str(tmp_path), "--jobs", "2"])
    assert res.exit_code == 0, res.output
    assert seen == [(2, 1)]
    assert parallel.inner_workers() == 2


def test_fork_map_stops_where_asked():
    seen = []
    out = parallel.fork_map(lambda j: seen.append(j) or j * 10, [1, 2, 3, 4], False, stop=lambda i, r: r == 20)
    assert out == [10, 20] and seen == [1, 2]


@pytest.mark.parametrize("trimmed", [False, True])
def test_start_beside_the_first_round_gives_the_same_report(monkeypatch, trimmed):
    """The start's state fitted beside the first round's candidates (core._free_start_beside_round, on
    slow coupled fits) reports what fitting it first does: where the start is kept steady (the whole
    record) and where it is fitted (trimmed a second after its only step: the round is made again).
    Run in-process here (the fork map's serial path, with the same stop rule)."""
    from rig.diagnosis import core, diagnose
    from rig.diagnosis.transforms import trim
    from rig.sim.synth import SynthSpec, make_record

    trial, _ = make_record(SynthSpec(protocol=[(2.0, 10.0), (38.0, 1.0)], duration_s=40.0, rate_hz=25.0,
                                     params={"mu0": 0.11, "A_mu": 1.1e-3, "B_mu": 4.0e-3, "L_um": 19.2},
                                     effects={"finite_stiffness": {"stiffness_kN_per_m": 300.0}}, with_ref=False,
                                     seed=5))
    trial.metadata["position_source"] = "load_point"
    if trimmed:
        trial = trim(trial)
    plain = diagnose(trial).report()
    calls = []
    real = core._free_start_beside_round

    def spy(*a, **k):
        out = real(*a, **k)
        calls.append(out is None)  # None: the start changed the model, the round was made again
        return out

    monkeypatch.setattr(core, "CANDIDATES_PARALLEL_MIN_S", -1.0)
    monkeypatch.setattr(core, "inner_workers", lambda: 2)
    monkeypatch.setattr(core, "can_fork", lambda: True)
    monkeypatch.setattr(parallel, "can_fork", lambda: False)  # the jobs themselves in this process
    monkeypatch.setattr(core, "_free_start_beside_round", spy)
    beside = diagnose(trial).report()
    assert calls and calls[0] is trimmed
    assert beside == plain
