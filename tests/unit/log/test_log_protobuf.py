"""/raw in protobuf (rig.LoopBlock): decoded by a reader that knows nothing of rig (the ``mcap`` library and
mcap-protobuf-support's generic decoder, message classes built from the FileDescriptorSet in the file),
field by field against ``rig export --rate raw``; the same trial in the older v2 layout exports the same CSV."""

from __future__ import annotations

from pathlib import Path
import re

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from typer.testing import CliRunner

import rig
from rig.cli import app
from rig.data import read_csv
from rig.log import BLOCK_KEYS, TrialLogWriter


runner = CliRunner()
T0_NS = 1_700_000_000_000_000_000
#: what a person reads from a field name's unit suffix (no rig code involved)
SUFFIX = [("_10nm_per_s", 1e-2), ("_per_32767", 1 / 32767), ("_per_100000", 1e-5), ("_10nm", 1e-2),
          ("_nm", 1e-3), ("_cN", 1e-2), ("_mN", 1e-3), ("_uN", 1e-6), ("_um", 1.0), ("_N", 1.0), ("_s", 1.0),
          ("", 1.0)]
#: the CSV column each field is (export names)
CSV_NAME = {"t_s": "time_s", "position_nm": "position_um", "position_ref_um": "position_ref_um",
            "friction_cN": "friction_N", "normal_1_cN": "normal_1_N", "normal_2_cN": "normal_2_N",
            "valve_cmd_per_32767": "valve_cmd", "pid_p_mN": "pid_p", "pid_i_mN": "pid_i", "pid_d_N": "pid_d",
            "dither_uN": "dither", "true_position_10nm": "true_position_um",
            "true_velocity_10nm_per_s": "true_velocity_um_s", "true_mu_per_100000": "true_mu", "spool_per_32767": "spool"}
#: a fixed identity: these tests write the same trial twice and compare the files (the writer gives
#: every other log a new uuid4 trial_uid, issue 21)
TRIAL_UID = "00000000-0000-4000-8000-000000000001"
#: one quantization step of each stored column (the devices' counts), in the CSV's unit
STEP = {"position_um": 0.076, "position_ref_um": 1e-3, "friction_N": 1e-2, "normal_1_N": 1e-2, "normal_2_N": 1e-2,
        "valve_cmd": 1 / 32767, "pid_p": 1e-3, "pid_i": 1e-3, "pid_d": 1e-6, "dither": 1e-6,
        "true_position_um": 1e-2, "true_velocity_um_s": 1e-2, "true_mu": 1e-5, "time_s": 1e-9, "spool": 1 / 32767}


def blocks(n_blocks=4, n=500, seed=3):
    rng = np.random.default_rng(seed)
    out = []
    for b in range(n_blocks):
        t = (b * n + np.arange(n)) / 1000.0
        blk = {k: rng.normal(size=n) for k in BLOCK_KEYS}
        blk["t_s"] = t
        blk["position_ref_um"] = 500 + 2.0 * t
        blk["position_um"] = blk["position_ref_um"] + rng.normal(size=n) * 0.2
        blk["friction_N"] = 20 + rng.normal(size=n) * 0.25
        blk["normal_1_N"] = 100 + rng.normal(size=n) * 0.25
        blk["normal_2_N"] = 100 - rng.normal(size=n) * 0.25
        blk["valve_cmd"] = np.clip(rng.normal(size=n) * 0.2, -1, 1)
        blk["pid_i"] = 3.0 + np.cumsum(rng.normal(size=n)) * 1e-3
        blk["dither"] = 0.01 * np.cos(np.pi * np.arange(n))
        blk["true_mu"] = 0.1 + rng.normal(size=n) * 1e-3
        out.append(blk)
    out[1]["pid_p"][7] = np.nan  # a fault sample: NaN in the CSV, 0 + nonfinite_* in the message
    return out


def write(path, raw_format="protobuf"):
    w = TrialLogWriter(path, metadata={"lubricant": "boundary", "normal_force_N": 100.0, "recipe": "unit",
                                 "trial_uid": TRIAL_UID},  # one trial written twice: same identity
                       start_time_ns=T0_NS, raw_format=raw_format, threaded=False, fsync=False)
    for b in blocks():
        w.write_block(b)
    w.close()


def export(path, out, rate="raw"):
    r = runner.invoke(app, ["export", str(path), "-o", str(out), "--rate", rate])
    assert r.exit_code == 0, r.output
    return out


def unit_of(field: str) -> float:
    return next(scale for suffix, scale in SUFFIX if field.endswith(suffix))


def test_generic_protobuf_decoder_matches_export_within_one_step(tmp_path):
    path = tmp_path / "t.mcap"
    write(path)
    cols: dict[str, list] = {}
    nonfinite = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        n0 = 0
        for schema, channel, message, msg in reader.iter_decoded_messages(topics=["/raw"]):
            assert (schema.name, schema.encoding, channel.message_encoding) == ("rig.LoopBlock", "protobuf",
                                                                                 "protobuf")
            assert message.log_time == T0_NS + round(msg.t0_s * 1e9)
            n = len(msg.t_s)
            for f in msg.DESCRIPTOR.fields:
                if f.is_repeated and not f.name.startswith("nonfinite"):
                    vals = list(getattr(msg, f.name))
                    assert len(vals) == n, f.name  # one value per sample: plottable against t_s[:]
                    cols.setdefault(f.name, []).extend(vals)
            nonfinite += [(num, n0 + i) for num, i in zip(msg.nonfinite_field, msg.nonfinite_index)]
            n0 += n
    csv = read_csv(export(path, tmp_path / "raw.csv"))
    table = {"time_s": csv.time_s, **{k: getattr(csv, k) for k in ("position_um", "friction_N", "normal_1_N",
                                                                        "normal_2_N", "position_ref_um",
                                                                        "valve_cmd")}, **csv.extra}
    assert set(CSV_NAME) == set(cols)
    for field, vals in cols.items():
        name = CSV_NAME[field]
        got = np.asarray(vals, dtype=float) * unit_of(field)
        want = table[name]
        assert got.size == want.size == 2000
        fin = np.isfinite(want)
        err = np.abs(got[fin] - want[fin]).max()
        assert err <= STEP[name] * (1 + 1e-6) + 1e-12 * np.abs(want[fin]).max(), (field, err)
    # the NaN sample: a plain 0 in its field, listed in nonfinite_field / nonfinite_index
    assert len(nonfinite) == 1 and nonfinite[0][1] == 507 and np.isnan(csv.extra["pid_p"][507])
    assert cols["pid_p_mN"][507] == 0


@pytest.mark.parametrize("rate", ["raw", "25"])
def test_old_and_new_layouts_export_the_same_csv(tmp_path, rate):
    for fmt in ("v2", "protobuf"):
        write(tmp_path / f"{fmt}.mcap", fmt)
        export(tmp_path / f"{fmt}.mcap", tmp_path / f"{fmt}.csv", rate)
    old, new = ((tmp_path / f"{f}.csv").read_text() for f in ("v2", "protobuf"))
    assert old == new and old.count("\n") > 50


def test_field_names_carry_units():
    from rig.log.loopblock import DISPLAY

    for key, (name, kind, unit) in DISPLAY.items():
        assert re.fullmatch(r"[a-z_0-9]+(_um|_nm|_10nm|_cN|_mN|_uN|_N|_per_32767|_per_100000|_10nm_per_s)", name), name
        assert unit == pytest.approx(unit_of(name)) or kind != "sint64", name


def test_cold_kernels_says_when_a_first_call_compiles(tmp_path, monkeypatch):
    import os

    from rig.commands import warmup

    monkeypatch.setattr(warmup, "_RIG", tmp_path)
    src = tmp_path / "mod.py"
    src.write_text("x = 1\n")
    assert warmup.cold_kernels(["mod.py"])  # no cache at all
    (tmp_path / "__pycache__").mkdir()
    idx = tmp_path / "__pycache__" / "mod.kernel-3.py311.nbi"
    idx.write_bytes(b"")
    os.utime(src, (1e9, 1e9))
    assert not warmup.cold_kernels(["mod.py"])  # cache newer than the source
    os.utime(src, (2e9, 2e9))
    assert warmup.cold_kernels(["mod.py"])  # the source changed since


@pytest.mark.parametrize("fmt, encoding", [(None, "protobuf"), ("v2", "rig.columns.v2")])
def test_recipe_chooses_the_raw_layout(tmp_path, fmt, encoding):
    from pathlib import Path
    from types import SimpleNamespace

    from rig.config import default_profile_path, load_profile, parse_recipe
    from rig.session.logfile import open_log

    text = (Path(rig.__file__).resolve().parents[1] / "config" / "recipes" / "smoke.yaml").read_text()
    if fmt:
        text = text.replace("log:\n", f"log:\n  raw_format: {fmt}\n", 1)
    recipe = parse_recipe(text, "smoke.yaml")
    w = open_log(tmp_path / "r.mcap", SimpleNamespace(loop_rate_hz=1000.0), recipe,
                 load_profile(default_profile_path()), {})
    w.write_block(blocks(2, 100)[0])
    w.close()
    with open(tmp_path / "r.mcap", "rb") as fh:
        chans = make_reader(fh).get_summary().channels.values()
    assert {c.topic: c.message_encoding for c in chans}["/raw"] == encoding


def test_small_real_time_chunks_are_compacted_at_close(tmp_path):
    """A trial logged in real time closes a chunk every second; at close the file is rewritten into
    large chunks (atomically): smaller, the same data, events and metadata."""
    from rig.log import read_metadata, read_trial

    def run(name, compact):
        w = TrialLogWriter(tmp_path / name, start_time_ns=T0_NS, threaded=False, fsync=False, compact=compact,
                           metadata={"lubricant": "boundary", "trial_uid": TRIAL_UID})
        for b in blocks(130, 50):
            w.write_block(b)
            w.flush()  # as the hardware's 0.5-1 s flushes
        w.close()
        return w

    plain, packed = run("plain.mcap", False), run("packed.mcap", True)
    assert plain.compacted is None and packed.compacted["chunks_before"] >= 130
    with open(tmp_path / "packed.mcap", "rb") as fh:
        summary = make_reader(fh, validate_crcs=True).get_summary()
    assert len(summary.chunk_indexes) < 6
    assert (tmp_path / "packed.mcap").stat().st_size < 0.9 * (tmp_path / "plain.mcap").stat().st_size
    a, b = (read_trial(tmp_path / n, "raw") for n in ("plain.mcap", "packed.mcap"))
    assert a.columns().keys() == b.columns().keys()
    for k, v in a.columns().items():
        assert np.array_equal(np.asarray(v), np.asarray(b.columns()[k]), equal_nan=True), k
    assert [e["kind"] for e in a.events] == [e["kind"] for e in b.events]
    ma, mb = (read_metadata(tmp_path / n) for n in ("plain.mcap", "packed.mcap"))
    for m in (ma, mb):
        m["trial_end"].pop("ended_utc")  # the two runs ended at different times
    assert ma == mb
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("ratio_int", [True, False])
def test_compiled_encoder_stores_the_counts_numpy_computes(ratio_int):
    """The one-pass kernel (quantize, clip, zigzag varints without the GIL) stores, field by field, the
    integers the numpy formula gives (the encoder before it), on values over the whole range, at the clip
    limits, at half steps and with a NaN (stored as 0, its place recorded)."""
    from rig.log.loopblock import LoopBlockEncoder, unpack_varints
    from rig.log.schemas import device_columns

    cols = device_columns()
    keys = ("t_s", "friction_N", "normal_1_N", "valve_cmd", "pid_i", "true_mu")
    enc = LoopBlockEncoder(lambda k: cols.get(k, cols["t_s"]), 1000.0)
    enc.plan(keys)
    if not ratio_int:  # the display unit from the count's physical value (a layout with an offset)
        enc._ratio_int = False
        enc._unit_off = np.linspace(-0.5, 0.5, len(enc._ints))
    rng = np.random.default_rng(7)
    n = 500
    m = np.stack([rng.normal(0, 1, n) * 10.0 ** rng.integers(-3, 6) for _ in enc._ints])
    m[:, :4] = [1e300, -1e300, 0.005, -0.015]  # clipped, clipped, half steps
    for nan in (False, True):
        if nan:
            m[2, 9] = np.nan
        with np.errstate(invalid="ignore"):
            q = np.rint((m - enc._off[:, None]) * enc._inv_q[:, None])
        q[~np.isfinite(q)] = 0.0
        q = np.clip(q, enc._lo[:, None], enc._hi[:, None]).astype(np.int64)
        want = q * enc._ratio_i[:, None] if ratio_int else \
            np.rint(q * enc._ratio_f[:, None] + enc._unit_off[:, None]).astype(np.int64)
        out, ends, nan_f, nan_i = np.zeros(m.size * 10, np.uint8), np.zeros(m.shape[0], np.int64), [], []
        if enc._quant(m, out, ends) < 0:
            enc._pack_nonfinite(m, out, ends, nan_f, nan_i)
        assert nan == bool(nan_f) and (not nan or (nan_f[0].tolist(), nan_i[0].tolist()) ==
                                       ([enc._ints[2].number], [9]))
        starts = np.concatenate(([0], ends[:-1]))
        for r in range(m.shape[0]):
            assert np.array_equal(unpack_varints(out[starts[r]:ends[r]], zigzag=True), want[r])


@pytest.mark.parametrize("keys", [tuple(BLOCK_KEYS), ("t_s", "position_um", "friction_N", "imported_thing")])
def test_schema_written_by_hand_is_what_descriptor_pb2_serializes(keys):
    """The FileDescriptorSet rig writes field by field (so a trial does not import protobuf) is the one the
    protobuf package builds and serializes from the same fields."""
    from google.protobuf import descriptor_pb2 as d

    from rig.log.loopblock import (F_NAN_FIELD, F_NAN_INDEX, F_RATE, F_T, F_T0, file_descriptor_set,
                                   plan_fields)
    from rig.log.schemas import device_columns

    cols = device_columns()
    fields = plan_fields(keys, lambda k: cols.get(k, cols["t_s"]))
    fds = d.FileDescriptorSet()
    m = fds.file.add(name="rig/loop_block.proto", package="rig", syntax="proto3").message_type.add(name="LoopBlock")
    T = d.FieldDescriptorProto
    types = {"double": T.TYPE_DOUBLE, "float": T.TYPE_FLOAT, "sint64": T.TYPE_SINT64, "uint32": T.TYPE_UINT32}
    for name, num in (("t0_s", F_T0), ("rate_hz", F_RATE)):
        m.field.add(name=name, number=num, type=T.TYPE_DOUBLE, label=T.LABEL_OPTIONAL, json_name=name)
    for name, num, kind in (("nonfinite_field", F_NAN_FIELD, "uint32"), ("nonfinite_index", F_NAN_INDEX, "uint32"),
                            ("t_s", F_T, "double")) + tuple((p.name, p.number, p.kind) for p in fields):
        m.field.add(name=name, number=num, type=types[kind], label=T.LABEL_REPEATED, json_name=name)
    assert file_descriptor_set(fields) == fds.SerializeToString()
    assert len(fields) == len(keys) - 1  # every column but t_s, a field of its own
