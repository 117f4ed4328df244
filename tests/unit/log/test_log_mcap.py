"""The MCAP trial log: round trip (v2 device counts), layout, v1 compatibility, CRC-verified reads,
corrupt chunks, flushing, truncation and recovery, epoch log_time, listeners."""

from __future__ import annotations

import json
import re
import struct
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

import rig
from rig.data import DataFormatError
from rig.log import (BLOCK_KEYS, EVENTS_TOPIC, LOG25_TOPIC, RAW_TOPIC, STATS_TOPIC,


                     LogDamageWarning, TrialLogWriter, read_metadata, read_trial, recover, trial_info)
from rig.log.figures import BlockFigures
from rig.log.schemas import DEVICE_COLUMNS, decode_v2

V1_FILE = Path(rig.__file__).resolve().parents[1] / "tests" / "data" / "v1-sim-1khz.mcap"
STD = ("position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd")
T0_NS = 1_700_000_000_123_456_789  # 2023-11-14: a fixed wall-clock start (more digits than a float64 holds)


def make_blocks(n_blocks=50, n=100, rate=1000.0, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for b in range(n_blocks):
        t = (b * n + np.arange(n)) / rate
        blk = {k: rng.normal(size=n) * 10 for k in BLOCK_KEYS}
        blk["t_s"] = t
        blk["position_ref_um"] = 500 + 2.0 * t
        blk["position_um"] = 0.076 * np.round((blk["position_ref_um"] + rng.normal(size=n) * 0.1) / 0.076)
        blk["normal_1_N"] = 100 + rng.normal(size=n)
        blk["normal_2_N"] = 100 + rng.normal(size=n)
        blk["friction_N"] = 20 + rng.normal(size=n)
        blk["valve_cmd"] = np.clip(rng.normal(size=n) * 0.1, -1, 1)
        blk["true_mu"] = 0.1 + rng.normal(size=n) * 1e-3
        out.append(blk)
    return out


def concat(blocks):
    return {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}


def write_log(path, blocks, **kw):
    kw.setdefault("start_time_ns", T0_NS)
    w = TrialLogWriter(path, metadata={"lubricant": "boundary", "normal_force_N": 100.0, "seed": 7,
                                       "recipe": "unit"},
                       recipe_yaml="name: unit\n", recipe={"name": "unit"}, profile={"name": "p"}, **kw)
    for i, b in enumerate(blocks):
        w.write_block(b)
        if i == 10:
            w.event(float(b["t_s"][0]), "velocity_step", v1_um_s=1.0, v2_um_s=2.0, x_um=np.float64(501.0))
            w.loop_stats(float(b["t_s"][-1]), {"ticks": 1100, "realtime_factor": np.float64(200.0),
                                               "bad": float("nan")})
    return w


def column(trial, key):
    if key == "t_s":
        return trial.time_s
    return getattr(trial, key) if key in STD else trial.extra[key]


@pytest.mark.parametrize("threaded", [True, False])
def test_round_trip_raw_device_counts_and_25hz(tmp_path, threaded):
    blocks = make_blocks()
    path = tmp_path / "t.mcap"
    write_log(path, blocks, threaded=threaded).close()
    ref = concat(blocks)

    raw = read_trial(path, channel="raw")
    assert len(raw) == 5000
    for k in BLOCK_KEYS:
        col = DEVICE_COLUMNS[k]
        step = col.scale if np.dtype(col.dtype).kind == "i" else 1e-6 * np.abs(ref[k]).max()
        err = np.abs(column(raw, k) - ref[k]).max()
        assert err <= 0.5 * step + 1e-12 * np.abs(ref[k]).max(), (k, err, step)
    assert np.array_equal(raw.position_um, ref["position_um"])  # on the LVDT grid: exact
    assert np.abs(raw.time_s - ref["t_s"]).max() < 1e-12
    assert set(raw.extra) == set(BLOCK_KEYS) - {"t_s", *STD}

    dec = read_trial(path)  # default: the 25 Hz channel, block means of the /raw device values
    assert dec.metadata["channel"] == "25hz"
    assert len(dec) == 5000 // 40
    # rig.log.decimate: the mean of each 40-tick interval, time-stamped at its centre
    np.testing.assert_allclose(dec.time_s, ref["t_s"].reshape(-1, 40).mean(axis=1), rtol=0, atol=1e-9)
    for k in STD:
        col = DEVICE_COLUMNS[k]
        # printed with two more decimals than one count
        tol = 0.006 * col.scale if np.dtype(col.dtype).kind == "i" else 1e-9
        np.testing.assert_allclose(getattr(dec, k), getattr(raw, k).reshape(-1, 40).mean(axis=1), rtol=0,
                                   atol=tol)
    assert dec.extra == {}

    kinds = [e["kind"] for e in dec.events]
    assert "velocity_step" in kinds and kinds[0] == "log_start" and kinds[-1] == "log_end"
    step = next(e for e in dec.events if e["kind"] == "velocity_step")
    assert step["v2_um_s"] == 2.0 and step["x_um"] == 501.0 and step["t_s"] == pytest.approx(1.0)
    assert dec.metadata["lubricant"] == "boundary" and dec.normal_force_N == 100.0
    assert dec.metadata["seed"] == "7" and dec.metadata["status"] == "completed"
    meta = read_metadata(path)
    assert json.loads(meta["recipe"]["json"]) == {"name": "unit"}
    assert json.loads(meta["rig_profile"]["json"]) == {"name": "p"}
    assert meta["trial"]["start_time_ns"] == str(T0_NS)


def test_layout_schemas_chunks_index_epoch_log_time(tmp_path):
    path = tmp_path / "t.mcap"
    write_log(path, make_blocks(), chunk_size=16_000).close()
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {RAW_TOPIC, LOG25_TOPIC, EVENTS_TOPIC, STATS_TOPIC}
        raw = topics[RAW_TOPIC]
        # a well-known encoding: protobuf, its FileDescriptorSet in the file, units in the field names
        assert raw.message_encoding == "protobuf"
        sch = summary.schemas[raw.schema_id]
        assert (sch.name, sch.encoding) == ("rig.LoopBlock", "protobuf")
        from google.protobuf import descriptor_pb2
        fds = descriptor_pb2.FileDescriptorSet.FromString(sch.data)
        names = {f.name for f in fds.file[0].message_type[0].field}
        assert {"t_s", "position_nm", "position_ref_um", "friction_cN", "normal_1_cN", "normal_2_cN",
                "valve_cmd_per_32767", "pid_p_mN", "pid_i_mN", "pid_d_N", "dither_uN"} <= names
        rig_cols = {c[0]: c for c in json.loads(raw.metadata["rig_columns"])}
        assert rig_cols["position_um"][2:] == ["position_nm", "sint64", 1e-3, 0.076, 0.0]
        assert raw.metadata["json_twin"] == LOG25_TOPIC
        for c in topics.values():
            if c.topic != RAW_TOPIC:
                assert c.message_encoding == "json"
                assert summary.schemas[c.schema_id].encoding == "jsonschema"
        assert len(summary.chunk_indexes) > 1
        assert all(ci.compression == "zstd" and ci.message_index_offsets for ci in summary.chunk_indexes)
        by_topic = {c.topic: summary.statistics.channel_message_counts[cid] for cid, c in summary.channels.items()}
        assert by_topic[RAW_TOPIC] == 50 and by_topic[LOG25_TOPIC] == 125
        # log_time: wall-clock ns since the epoch = start + t_s; t_s stays a field
        assert summary.statistics.message_start_time == T0_NS
        for _, _, m in list(reader.iter_messages(topics=[LOG25_TOPIC]))[:5]:
            d = json.loads(m.data)
            assert m.log_time == T0_NS + round(d["t_s"] * 1e9)
            assert set(d) == {"t_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um",
                              "valve_cmd", "mu"}
            assert d["mu"] == pytest.approx(d["friction_N"] / (d["normal_1_N"] + d["normal_2_N"]), rel=1e-5)
        assert [a.name for a in reader.iter_attachments()] == ["recipe.yaml"]
        stats = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[STATS_TOPIC])]
        assert stats[0]["bad"] is None and stats[0]["realtime_factor"] == 200.0


def test_default_start_time_is_now(tmp_path):
    before = time.time_ns()
    w = TrialLogWriter(tmp_path / "n.mcap")
    w.write_block(make_blocks(1)[0])
    w.close()
    with open(tmp_path / "n.mcap", "rb") as fh:
        st = make_reader(fh).get_summary().statistics
    assert before <= st.message_start_time <= time.time_ns()


def test_v2_block_decodes_as_documented(tmp_path):
    """(the layout before protobuf, still written on request and read) b'RIG2', u32 header length, JSON header with [key, dtype, filter, scale, offset, nbytes], columns."""
    import zstandard

    blocks = make_blocks(3, n=1000)
    path = tmp_path / "b.mcap"
    write_log(path, blocks, raw_format="v2").close()
    with open(path, "rb") as fh:
        msgs = [m for _, _, m in make_reader(fh).iter_messages(topics=[RAW_TOPIC])]
    assert len(msgs) == 3
    for blk, m in zip(blocks, msgs):
        data = m.data
        assert data[:4] == b"RIG2"
        (hlen,) = struct.unpack("<I", data[4:8])
        head = json.loads(data[8:8 + hlen])
        assert (8 + hlen) % 8 == 0 and head["n"] == 1000 and head["t0_s"] == blk["t_s"][0]
        assert m.log_time == T0_NS + round(head["t0_s"] * 1e9)
        off = 8 + hlen
        for key, dtype, flt, scale, offset, nbytes in head["columns"]:
            b = data[off:off + nbytes]
            off += nbytes
            if key != "position_um":
                continue
            assert (dtype, flt, scale) == ("<i4", "shuffle+zstd", 0.076)
            b = zstandard.ZstdDecompressor().decompress(b, max_output_size=4000)
            counts = np.frombuffer(b, np.uint8).reshape(4, 1000).T.copy().view("<i4").ravel()
            assert np.array_equal(counts * scale + offset, blk["position_um"])
        assert off == len(data)


def test_nan_and_inf_survive_as_nan(tmp_path):
    blocks = make_blocks(5)
    blocks[1]["friction_N"][3] = np.nan
    blocks[1]["valve_cmd"][20] = np.inf  # tick 120: also the 4th 25 Hz sample
    blocks[2]["pid_d"][5] = np.nan       # a float32 column
    path = tmp_path / "j.mcap"
    write_log(path, blocks).close()
    raw = read_trial(path, "raw")
    assert np.isnan(raw.friction_N[103]) and np.isnan(raw.valve_cmd[120]) and np.isnan(raw.extra["pid_d"][205])
    assert np.isfinite(raw.friction_N).sum() == 499
    dec = read_trial(path, "25hz")
    assert np.isnan(dec.valve_cmd[3]) and np.isnan(dec.valve_cmd).sum() == 1


def test_mu_on_log25_is_null_where_normals_sum_to_zero(tmp_path):
    blk = make_blocks(1)[0]
    blk["normal_1_N"][:] = 0.0
    blk["normal_2_N"][:] = 0.0
    path = tmp_path / "z.mcap"
    w = TrialLogWriter(path)
    w.write_block(blk)  # no ZeroDivisionError anywhere
    w.close()
    with open(path, "rb") as fh:
        rows = [json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=[LOG25_TOPIC])]
    assert rows and all(r["mu"] is None for r in rows)
    assert np.isnan(read_trial(path).mu).all()
    fig = BlockFigures()
    fig.add(blk)
    assert np.isnan(fig.mean_mu) and fig.mean_friction_N == pytest.approx(np.mean(blk["friction_N"]))


def test_v1_log_from_the_previous_writer_still_reads():
    """tests/data/v1-sim-1khz.mcap: written by the old rig.columns.v1 writer (float64 columns, log_time from 0)."""
    raw = read_trial(V1_FILE, "raw")
    dec = read_trial(V1_FILE)
    assert len(raw) == 1678 and np.allclose(np.diff(raw.time_s), 1e-3)
    assert {"pid_p", "true_mu"} <= set(raw.extra)
    assert 99 < np.median(raw.normal_1_N) < 102 and 495 < np.median(raw.position_um) < 510
    assert np.array_equal(dec.time_s, raw.time_s[::40])            # v1 float64: the 25 Hz values are exact
    assert np.array_equal(dec.friction_N, raw.friction_N[::40])
    assert dec.metadata["lubricant"] == "boundary" and dec.normal_force_N == 100.0
    info = trial_info(V1_FILE)
    assert info["complete"] and info["duration_s"] == pytest.approx(1.677, abs=0.01)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_mcap_reader_validates_every_chunk_crc(tmp_path, compression):
    blocks = make_blocks(40)
    path = tmp_path / "v.mcap"
    write_log(path, blocks, chunk_size=20_000, compression=compression).close()
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        assert sum(1 for _ in reader.iter_messages()) == summary.statistics.message_count
        assert summary.statistics.chunk_count == len(summary.chunk_indexes) > 2
    expected = {"zstd": "zstd", "lz4": "lz4", "none": ""}[compression]
    assert all(ci.compression == expected for ci in summary.chunk_indexes)
    assert len(read_trial(path, "raw")) == 4000


def test_compressing_thread_and_decimation_in_the_writer_change_no_message(tmp_path):
    """Full zstd chunks compressed in a thread of their own (written in order) and the 25 Hz decimation in
    the writer's thread give the messages of an unthreaded, uncompressed log, CRCs and indexes valid; so
    does a listener that comes after the first block (the decimation goes back to the loop's thread)."""
    blocks = make_blocks(40)

    def messages(path, listen_from=None, **kw):
        got: list = []
        w = TrialLogWriter(path, start_time_ns=T0_NS, metadata={"trial_uid": "u"}, flush_interval_s=1e9, **kw)
        for i, b in enumerate(blocks):
            if i == listen_from:
                w.add_listener(lambda kind, payload: got.append(kind))
            w.write_block(b)
        w.close()
        with open(path, "rb") as fh:
            reader = make_reader(fh, validate_crcs=True)
            msgs = [(c.topic, m.log_time, m.sequence, m.data) for _, c, m in reader.iter_messages()]
            return msgs, reader.get_summary(), got

    ref, _, _ = messages(tmp_path / "ref.mcap", threaded=False, compression="none")
    fast, summary, _ = messages(tmp_path / "fast.mcap", chunk_size=20_000)
    late, _, got = messages(tmp_path / "late.mcap", chunk_size=20_000, listen_from=20)
    assert len(summary.chunk_indexes) > 5 and {ci.compression for ci in summary.chunk_indexes} == {"zstd"}
    assert fast == ref and late == ref
    assert sum(t == LOG25_TOPIC for t, *_ in ref) == 100 and got.count("samples") == 20


def test_corrupt_chunk_is_named_skipped_and_never_carried_forward(tmp_path, corrupt_middle_chunk):
    blocks = make_blocks(60)
    good = tmp_path / "good.mcap"
    write_log(good, blocks, chunk_size=20_000).close()
    bad = tmp_path / "bad.mcap"
    victim = corrupt_middle_chunk(good, bad)
    t_lo = (victim.message_start_time - T0_NS) / 1e9
    ref = read_trial(good, "raw")

    with pytest.warns(LogDamageWarning, match=r"CRC mismatch .* t = \d+\.\d+\.\.\d+\.\d+ s .*/raw"):
        raw = read_trial(bad, "raw")
    assert raw.warnings and f"{t_lo:.3f}" in raw.warnings[0]
    assert 0 < len(raw) < len(ref)
    # every value kept is the intact one: nothing from the corrupt chunk
    keep = np.isin(ref.time_s, raw.time_s)
    assert np.array_equal(raw.friction_N, ref.friction_N[keep])
    lost = ref.time_s[~keep]
    assert lost.min() >= t_lo - 1e-9
    with pytest.raises(DataFormatError, match="damaged chunk"):
        read_trial(bad, "raw", strict=True)

    info = trial_info(bad)
    assert not info["complete"] and len(info["corrupt_chunks"]) == 1
    assert RAW_TOPIC in info["corrupt_chunks"][0]["channels"]

    fixed = tmp_path / "fixed.mcap"
    res = recover(bad, fixed)
    assert not res["complete_before"] and len(res["damage"]) == 1
    with open(fixed, "rb") as fh:  # passes the CRC check, and holds only intact values
        assert sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages()) > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogDamageWarning)
        rec = read_trial(fixed, "raw")
    assert np.array_equal(rec.time_s, raw.time_s) and np.array_equal(rec.friction_N, raw.friction_N)
    assert "corrupt chunk" in trial_info(fixed)["metadata"]["recovery"]["recovery_error"]


def test_decimation_continues_across_odd_blocks(tmp_path):
    """The 25 Hz samples are the means of each 40 loop ticks, whatever the block sizes."""
    ref = concat(make_blocks(10))
    path = tmp_path / "o.mcap"
    w = TrialLogWriter(path)
    edges = [0, 37, 100, 101, 333, 640, 1000]
    for a, b in zip(edges[:-1], edges[1:]):
        w.write_block({k: v[a:b] for k, v in ref.items()})
    w.close()
    np.testing.assert_allclose(read_trial(path).time_s, ref["t_s"][:1000].reshape(-1, 40).mean(axis=1),
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("threaded", [True, False])
def test_flush_makes_data_survive_a_crash(tmp_path, threaded):
    blocks = make_blocks(30)
    path = tmp_path / "c.mcap"
    w = write_log(path, blocks, flush_interval_s=0.0, threaded=threaded)  # flush + fsync after every block
    w.abort()  # crash: no footer, no summary
    with pytest.raises(DataFormatError, match="rig recover"):
        read_trial(path)
    info = trial_info(path)
    assert not info["complete"] and info["damage"]
    assert next(c["messages"] for c in info["channels"] if c["topic"] == RAW_TOPIC) == 30  # nothing lost
    fixed = tmp_path / "fixed.mcap"
    recover(path, fixed)
    assert len(read_trial(fixed, "raw")) == 3000


def test_recover_truncated_mid_chunk(tmp_path):
    blocks = make_blocks(200)
    full = tmp_path / "full.mcap"
    write_log(full, blocks, chunk_size=30_000).close()
    with open(full, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    assert len(chunks) >= 4
    victim = chunks[len(chunks) // 2]
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(full.read_bytes()[:victim.chunk_start_offset + victim.chunk_length // 2])

    with pytest.raises(DataFormatError, match="rig recover"):
        read_trial(bad)
    fixed = tmp_path / "fixed.mcap"
    res = recover(bad, fixed)
    assert res["error"] and not res["complete_before"]
    raw = read_trial(fixed, "raw")
    ref = read_trial(full, "raw")
    n = len(raw)
    assert 0 < n < 20000 and n % 100 == 0
    assert np.array_equal(raw.friction_N, ref.friction_N[:n])  # the complete chunks, intact
    assert raw.metadata["recovered"] == "true" and raw.metadata["lubricant"] == "boundary"
    info = trial_info(fixed)
    assert info["recovered"] and info["complete"]
    assert info["metadata"]["recovery"]["recovered_from"] == str(bad)
    assert info["attachments"][0]["name"] == "recipe.yaml"
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left


@pytest.mark.parametrize("content,what", [(b"not an mcap at all", "not an MCAP"),
                                          (b"\x89PNG\r\n\x1a\n" + bytes(40), "PNG"),
                                          (b"", "empty")])
def test_not_a_log_is_one_clear_error(tmp_path, content, what):
    p = tmp_path / "g.mcap"
    p.write_bytes(content)
    for fn in (lambda: recover(p, tmp_path / "out.mcap"), lambda: read_trial(p), lambda: trial_info(p)):
        with pytest.raises(DataFormatError, match=what):
            fn()
    assert not (tmp_path / "out.mcap").exists()
    with pytest.raises(DataFormatError, match="directory"):
        trial_info(tmp_path)


def test_context_manager_marks_interrupted(tmp_path):
    path = tmp_path / "i.mcap"
    with pytest.raises(KeyboardInterrupt):
        with TrialLogWriter(path) as w:
            for b in make_blocks(3):
                w.write_block(b)
            raise KeyboardInterrupt
    tr = read_trial(path, "raw")
    assert len(tr) == 300 and tr.metadata["status"] == "interrupted"


def test_scheduled_events_logged_when_reached(tmp_path):
    path = tmp_path / "e.mcap"
    w = TrialLogWriter(path)
    w.schedule_events([{"t_s": 0.25, "kind": "a"}, {"t_s": 0.05, "kind": "b"}, {"t_s": 9.0, "kind": "never"}])
    for b in make_blocks(3):
        w.write_block(b)
    w.close("interrupted")
    assert [e["kind"] for e in read_trial(path).events] == ["log_start", "b", "a", "log_end"]


def test_flush_at_least_every_second_of_wall_time(tmp_path, monkeypatch):
    import rig.log.writer as writer_mod

    clock = [1000.0]
    monkeypatch.setattr(writer_mod.time, "monotonic", lambda: clock[0])
    blocks = make_blocks(6)

    def raw_on_disk(path):
        return next((c["messages"] for c in trial_info(path)["channels"] if c["topic"] == RAW_TOPIC), 0)

    a = tmp_path / "a.mcap"
    w = TrialLogWriter(a)  # default flush_interval_s = 1.0
    for b in blocks:
        w.write_block(b)  # all within the same wall-clock second
    w.abort()
    assert raw_on_disk(a) == 0  # still in the open chunk: a crash now would lose < 1 s

    b_path = tmp_path / "b.mcap"
    w = TrialLogWriter(b_path)
    for b in blocks[:5]:
        w.write_block(b)
    clock[0] += 1.01  # a second of wall time later
    w.write_block(blocks[5])
    w.abort()
    assert raw_on_disk(b_path) == 6  # flushed (chunk closed + fsync) on the first block after 1 s


def test_writer_thread_error_surfaces(tmp_path):
    w = TrialLogWriter(tmp_path / "e.mcap")
    w._sink._sink.w = None  # break the sink: the next write fails in the thread
    with pytest.raises(RuntimeError, match="log writer thread failed"):
        for b in make_blocks(3):  # raised at the next call after the failure, at the latest by close()
            w.write_block(b)
        w.close()


def test_listeners_get_samples_events_and_loop_stats(tmp_path):
    """The hook for a live view: 25 Hz samples, events and loop statistics; a failing listener is detached."""
    got: list = []

    def broken(kind, payload):
        raise RuntimeError("viewer gone")

    w = TrialLogWriter(tmp_path / "l.mcap")
    w.add_listener(lambda kind, payload: got.append((kind, payload)))
    w.add_listener(broken)
    for i, b in enumerate(make_blocks(4)):
        w.write_block(b)
        w.event(float(b["t_s"][-1]), "marker", i=i)
        w.loop_stats(float(b["t_s"][-1]), {"ticks": 100})
    w.close()
    kinds = [k for k, _ in got]
    assert kinds.count("samples") == 4 and kinds.count("loop_stats") == 4
    assert kinds.count("event") >= 5  # markers and log_end
    samples = [p for k, p in got if k == "samples"]
    assert sum(len(p["t_s"]) for p in samples) == 10 and "mu" in samples[0]
    assert len(w.listener_errors) == 1 and "viewer gone" in w.listener_errors[0]
    assert read_trial(tmp_path / "l.mcap").metadata["status"] == "completed"


def test_foxglove_layout_plots_only_fields_the_log_has():
    """config/foxglove/rig-trial.json: every plotted path is a topic and field the writer produces; the 1 kHz
    tuning tab plots /raw's protobuf fields against /raw.t_s[:]."""
    from rig.log.loopblock import DISPLAY
    from rig.log.schemas import SAMPLE_FIELDS

    layout = json.loads((Path(rig.__file__).resolve().parents[1] / "config" / "foxglove" / "rig-trial.json").read_text())
    fields = {LOG25_TOPIC: set(SAMPLE_FIELDS), RAW_TOPIC: {name + "[:]" for name, _, _ in DISPLAY.values()},
              # sim: run_sim_trial's statistics; hardware: rig.hardware.timing's window
              STATS_TOPIC: {"realtime_factor", "tracking_error_rms_um", "late_p99_us", "late_max_us", "exec_p99_us"}}
    paths = []
    for pid, cfg in layout["configById"].items():
        for p in cfg.get("paths", []):
            topic, field = p["value"].split(".", 1)
            assert field in fields[topic], p["value"]
            if topic == RAW_TOPIC:  # x: the sample times of the same messages
                assert cfg["xAxisVal"] == "custom" and cfg["xAxisPath"]["value"] == "/raw.t_s[:]"
            paths.append(p["value"])
        if "topicPath" in cfg:
            assert cfg["topicPath"] == EVENTS_TOPIC
    for want in ("/log25.position_um", "/log25.position_ref_um", "/log25.friction_N", "/log25.normal_1_N",
                 "/log25.normal_2_N", "/log25.valve_cmd", "/loop_stats.late_p99_us", "/raw.position_nm[:]",
                 "/raw.position_ref_um[:]", "/raw.friction_cN[:]", "/raw.normal_1_cN[:]", "/raw.normal_2_cN[:]",
                 "/raw.valve_cmd_per_32767[:]", "/raw.pid_p_mN[:]", "/raw.pid_i_mN[:]", "/raw.pid_d_N[:]",
                 "/raw.dither_uN[:]", "/raw.spool_per_32767[:]"):
        assert want in paths

    def leaves(node):
        if isinstance(node, str):
            tabs = layout["configById"].get(node, {}).get("tabs") if node.startswith("Tab!") else None
            return [node] + [x for t in tabs for x in leaves(t["layout"])] if tabs else [node]
        return leaves(node["first"]) + leaves(node["second"])
    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    assert [t["title"] for t in layout["configById"]["Tab!main"]["tabs"]] == ["trial (25 Hz)", "tuning (1 kHz)"]


def test_trial_end_counts_what_the_file_holds(tmp_path):
    """One count: trial_end's events, raw blocks and 25 Hz samples are the messages `rig info` counts
    (log_end and the last partial 25 Hz sample included)."""
    from rig.log.reader import scan

    path = tmp_path / "c.mcap"
    write_log(path, make_blocks(n_blocks=12, n=125)).close()
    c = scan(path)
    end = next(dict(m.metadata) for m in reversed(c.metadata) if m.name == "trial_end")
    by_topic = {c.channels[cid].topic: n for cid, n in c.counts.items()}
    assert int(end["events"]) == by_topic[EVENTS_TOPIC] >= 3  # log_start, velocity_step, log_end
    assert int(end["raw_blocks"]) == by_topic[RAW_TOPIC] == 12
    assert int(end["samples_decimated"]) == by_topic[LOG25_TOPIC] == 38  # 1500 ticks: 37 intervals of 40 + 1


@pytest.mark.parametrize("n", [40, 7, 333])
def test_compiled_block_means_are_numpys_to_the_bit(n):
    """The writer's compiled 25 Hz decimation (rig.log.decimate.MatrixBlockMean: grid rounding and block
    means in one pass) gives the bits of the numpy BlockMean it replaced, across blocks that end
    mid-interval, with NaNs, and for the last partial interval."""
    from rig.log.decimate import BlockMean, MatrixBlockMean

    rng = np.random.default_rng(n)
    off, scale = np.array([0.0, 0.5, 0.0]), np.array([1.0, 0.01, 1 / 32767])
    mb, ref = MatrixBlockMean(n, [False, True, True], off, scale), BlockMean(n)
    for size in (1000, 37, 999, 1, 2500):
        m = rng.normal(0, 1, (3, size)) * np.array([[1e3], [10.0], [0.5]]) + 1e5 * (size == 37)
        m[2, 0] = np.nan
        g = m.copy()
        with np.errstate(invalid="ignore"):
            g[1:] = np.rint((g[1:] - off[1:, None]) / scale[1:, None]) * scale[1:, None] + off[1:, None]
        got, want = mb.push(m), ref.push({"m": g})
        assert (got is None) == (want is None)
        if got is not None:
            assert np.array_equal(got, want["m"], equal_nan=True)
    assert np.array_equal(mb.flush(), ref.flush()["m"], equal_nan=True)


def test_the_writers_records_in_one_pass_are_the_mcap_writers_own(tmp_path, monkeypatch):
    """The writer's one pass over a batch of messages (rig.log.writer._Sink._add_batch: no record object per
    message) gives the bytes of the ``mcap`` Writer's own ``add_message``, message by message: chunks,
    message indexes, chunk indexes and statistics; with chunks small enough that most blocks' 25 Hz messages
    are split across two, and a block with non-finite values."""
    from rig.log import writer as writer_mod

    blocks = make_blocks(8, n=1000)  # 25 samples at 25 Hz per block
    blocks[5]["friction_N"][3:70] = np.nan

    def write(path):
        w = TrialLogWriter(path, start_time_ns=T0_NS, metadata={"trial_uid": "u"}, flush_interval_s=1e9,
                           threaded=False, compression="none", chunk_size=1_500)
        for b in blocks:
            w.write_block(b)
        w.close()
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
        return re.sub(rb"\d{4}-\d\d-\d\dT[\d:.]+\+00:00", b"T", path.read_bytes()), summary  # but the end's time

    ours, s_ours = write(tmp_path / "runs.mcap")
    monkeypatch.setattr(writer_mod._Sink, "_fast", property(lambda self: False))
    theirs, s_theirs = write(tmp_path / "mcap.mcap")
    assert len(s_ours.chunk_indexes) > 20 and s_ours.statistics.channel_message_counts == \
        s_theirs.statistics.channel_message_counts
    assert ours == theirs and s_ours.chunk_indexes == s_theirs.chunk_indexes
    assert s_ours.statistics == s_theirs.statistics
