"""The MCAP trial log: round trip, the 25 Hz channel, layout, flushing, truncation and recovery."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from rig.data import DataFormatError
from rig.log import (BLOCK_KEYS, EVENTS_TOPIC, LOG25_TOPIC, RAW_BINARY_ENCODING, RAW_TOPIC, STATS_TOPIC,
                     TrialLogWriter, read_metadata, read_trial, recover, trial_info)


def make_blocks(n_blocks=50, n=100, rate=1000.0, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for b in range(n_blocks):
        t = (b * n + np.arange(n)) / rate
        blk = {k: rng.normal(size=n) * 10 for k in BLOCK_KEYS}
        blk["t_s"] = t
        blk["position_ref_um"] = 500 + 2.0 * t
        blk["position_um"] = blk["position_ref_um"] + rng.normal(size=n) * 0.1
        blk["normal_1_N"] = 100 + rng.normal(size=n)
        blk["normal_2_N"] = 100 + rng.normal(size=n)
        blk["friction_N"] = 20 + rng.normal(size=n)
        out.append(blk)
    return out


def concat(blocks):
    return {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}


def write_log(path, blocks, **kw):
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


@pytest.mark.parametrize("threaded", [True, False])
def test_round_trip_raw_and_25hz(tmp_path, threaded):
    blocks = make_blocks()
    path = tmp_path / "t.mcap"
    w = write_log(path, blocks, threaded=threaded)
    w.close()
    ref = concat(blocks)

    raw = read_trial(path, channel="raw")
    assert len(raw) == 5000
    for k in BLOCK_KEYS:
        got = raw.time_s if k == "t_s" else (getattr(raw, k, None) if k in (
            "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um", "valve_cmd") else raw.extra[k])
        assert np.array_equal(got, ref[k]), k          # bit-exact (binary float64)
    assert set(raw.extra) == set(BLOCK_KEYS) - {"t_s", "position_um", "friction_N", "normal_1_N", "normal_2_N",
                                                "position_ref_um", "valve_cmd"}

    dec = read_trial(path)  # default: the 25 Hz channel
    assert dec.metadata["channel"] == "25hz"
    assert len(dec) == 5000 // 40
    assert np.array_equal(dec.time_s, ref["t_s"][::40])
    assert np.array_equal(dec.friction_N, ref["friction_N"][::40])
    assert np.array_equal(dec.valve_cmd, ref["valve_cmd"][::40])
    assert dec.extra == {}

    # events and metadata come along
    kinds = [e["kind"] for e in dec.events]
    assert "velocity_step" in kinds and kinds[0] == "log_start" and kinds[-1] == "log_end"
    step = next(e for e in dec.events if e["kind"] == "velocity_step")
    assert step["v2_um_s"] == 2.0 and step["x_um"] == 501.0 and step["t_s"] == pytest.approx(1.0)
    assert dec.metadata["lubricant"] == "boundary" and dec.normal_force_N == 100.0
    assert dec.metadata["seed"] == "7" and dec.metadata["status"] == "completed"
    assert dec.metadata["software_version"]
    meta = read_metadata(path)
    assert json.loads(meta["recipe"]["json"]) == {"name": "unit"}
    assert json.loads(meta["rig_profile"]["json"]) == {"name": "p"}


def test_layout_schemas_chunks_index(tmp_path):
    path = tmp_path / "t.mcap"
    write_log(path, make_blocks(), chunk_size=64_000).close()
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {RAW_TOPIC, LOG25_TOPIC, EVENTS_TOPIC, STATS_TOPIC}
        for c in topics.values():
            if c.topic == RAW_TOPIC:  # binary columns: no schema, the layout is in the channel metadata
                assert c.message_encoding == RAW_BINARY_ENCODING and c.schema_id == 0
                assert "little-endian" in c.metadata["layout"]
                continue
            assert c.message_encoding == "json"
            assert summary.schemas[c.schema_id].encoding == "jsonschema"
            json.loads(summary.schemas[c.schema_id].data)
        assert len(summary.chunk_indexes) > 1
        assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
        assert all(ci.message_index_offsets for ci in summary.chunk_indexes)  # message index kept
        counts = summary.statistics.channel_message_counts
        by_topic = {topics_c.topic: counts[cid] for cid, topics_c in summary.channels.items()}
        assert by_topic[RAW_TOPIC] == 50 and by_topic[LOG25_TOPIC] == 125
        # the 25 Hz channel: log_time is the sample time, one plain JSON object per sample
        msgs = list(reader.iter_messages(topics=[LOG25_TOPIC]))
        for _, _, m in msgs[:5]:
            d = json.loads(m.data)
            assert m.log_time == round(d["t_s"] * 1e9)
            assert set(d) == {"t_s", "position_um", "friction_N", "normal_1_N", "normal_2_N", "position_ref_um",
                              "valve_cmd"}
        names = [a.name for a in reader.iter_attachments()]
        assert names == ["recipe.yaml"]
        stats = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[STATS_TOPIC])]
        assert stats[0]["bad"] is None and stats[0]["realtime_factor"] == 200.0


def test_binary_raw_block_layout_decodes_as_documented(tmp_path):
    """A /raw message is b'RIGC', u32 header length, JSON header, then little-endian columns (docs/trial.md)."""
    import struct

    blocks = make_blocks(3, n=1000)
    path = tmp_path / "b.mcap"
    write_log(path, blocks).close()
    with open(path, "rb") as fh:
        msgs = [m for _, _, m in make_reader(fh).iter_messages(topics=[RAW_TOPIC])]
    assert len(msgs) == 3
    for blk, m in zip(blocks, msgs):
        data = m.data
        assert data[:4] == b"RIGC"
        (hlen,) = struct.unpack("<I", data[4:8])
        head = json.loads(data[8:8 + hlen])
        assert (8 + hlen) % 8 == 0
        assert head["n"] == 1000 and head["t0_s"] == blk["t_s"][0] and head["rate_hz"] == 1000.0
        assert m.log_time == round(head["t0_s"] * 1e9)
        assert head["fields"] == list(blk) and set(head["dtypes"]) == {"<f8"}
        cols = np.frombuffer(data, "<f8", offset=8 + hlen).reshape(len(head["fields"]), 1000)
        for key, col in zip(head["fields"], cols):
            assert np.array_equal(col, blk[key]), key


@pytest.mark.parametrize("compression,level", [("zstd", 1), ("zstd", -3), ("lz4", 0), ("none", 0)])
def test_chunks_crcs_and_message_index_are_valid_mcap(tmp_path, compression, level):
    """rig's own MCAP writer: the mcap reader checks the CRCs; every message index entry points at its message."""
    import struct

    from mcap.records import Chunk, MessageIndex
    from mcap.stream_reader import StreamReader

    blocks = make_blocks(40)
    path = tmp_path / "v.mcap"
    write_log(path, blocks, chunk_size=50_000, compression=compression, compression_level=level).close()
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        n_msgs = sum(1 for _ in reader.iter_messages())
        assert n_msgs == summary.statistics.message_count
        assert summary.statistics.chunk_count == len(summary.chunk_indexes) > 2
        assert [m.log_time for _, _, m in reader.iter_messages(topics=[LOG25_TOPIC])] == \
            [round(t * 1e9) for t in concat(blocks)["t_s"][::40]]
    expected = {"zstd": "zstd", "lz4": "lz4", "none": ""}[compression]
    assert all(ci.compression == expected for ci in summary.chunk_indexes)
    chunk = None
    checked = 0
    with open(path, "rb") as fh:
        for rec in StreamReader(fh, emit_chunks=True, validate_crcs=True).records:
            if isinstance(rec, Chunk):
                if rec.compression == "zstd":
                    import zstandard
                    chunk = zstandard.ZstdDecompressor().decompress(rec.data, max_output_size=rec.uncompressed_size)
                elif rec.compression == "lz4":
                    import lz4.frame
                    chunk = lz4.frame.decompress(rec.data)
                else:
                    chunk = rec.data
                assert len(chunk) == rec.uncompressed_size
            elif isinstance(rec, MessageIndex):
                for log_time, offset in rec.records:
                    op, _length, cid, _seq, t = struct.unpack_from("<BQHIQ", chunk, offset)
                    assert (op, cid, t) == (0x05, rec.channel_id, log_time)
                    checked += 1
    assert checked == n_msgs


def test_base64_raw_encoding_still_written_and_read(tmp_path):
    blocks = make_blocks(4)
    path = tmp_path / "b64.mcap"
    write_log(path, blocks, raw_encoding="base64").close()
    raw = read_trial(path, "raw")
    assert np.array_equal(raw.friction_N, concat(blocks)["friction_N"])
    with open(path, "rb") as fh:
        ch = {c.topic: c for c in make_reader(fh).get_summary().channels.values()}
    assert ch[RAW_TOPIC].message_encoding == "json"


def test_json_raw_encoding_and_nan(tmp_path):
    blocks = make_blocks(5)
    blocks[1]["friction_N"][3] = np.nan
    blocks[1]["valve_cmd"][20] = np.inf  # tick 120: also the 4th 25 Hz sample
    path = tmp_path / "j.mcap"
    write_log(path, blocks, raw_encoding="json").close()
    raw = read_trial(path, "raw")
    ref = concat(blocks)
    assert np.isnan(raw.friction_N[103]) and np.isnan(raw.valve_cmd[120])
    ok = np.isfinite(ref["friction_N"])
    assert np.array_equal(raw.friction_N[ok], ref["friction_N"][ok])
    dec = read_trial(path, "25hz")
    assert np.isnan(dec.valve_cmd[3]) and np.isnan(dec.valve_cmd).sum() == 1


def test_float32_raw_dtype(tmp_path):
    blocks = make_blocks(5)
    path = tmp_path / "f.mcap"
    write_log(path, blocks, raw_dtype="float32").close()
    raw = read_trial(path, "raw")
    ref = concat(blocks)
    assert np.array_equal(raw.time_s, ref["t_s"])  # time stays float64
    assert np.array_equal(raw.friction_N, ref["friction_N"].astype(np.float32).astype(float))


def test_decimation_continues_across_odd_blocks(tmp_path):
    """The 25 Hz samples are every 40th loop tick, whatever the block sizes."""
    ref = concat(make_blocks(10))
    path = tmp_path / "o.mcap"
    w = TrialLogWriter(path)
    edges = [0, 37, 100, 101, 333, 640, 1000]
    for a, b in zip(edges[:-1], edges[1:]):
        w.write_block({k: v[a:b] for k, v in ref.items()})
    w.close()
    dec = read_trial(path)
    assert np.array_equal(dec.time_s, ref["t_s"][:1000:40])


@pytest.mark.parametrize("threaded", [True, False])
def test_flush_makes_data_survive_a_crash(tmp_path, threaded):
    blocks = make_blocks(30)
    path = tmp_path / "c.mcap"
    w = write_log(path, blocks, flush_interval_s=0.0, threaded=threaded)  # flush (close chunk + fsync) after every block
    w.abort()  # crash: no footer, no summary
    with pytest.raises(DataFormatError, match="rig recover"):
        read_trial(path)
    info = trial_info(path)
    assert not info["complete"] and info["damage"]
    raw_count = next(c["messages"] for c in info["channels"] if c["topic"] == RAW_TOPIC)
    assert raw_count == 30  # nothing lost


def test_recover_truncated_mid_chunk(tmp_path):
    blocks = make_blocks(200)
    full = tmp_path / "full.mcap"
    write_log(full, blocks, chunk_size=100_000).close()
    with open(full, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    assert len(chunks) >= 4
    victim = chunks[len(chunks) // 2]
    cut = victim.chunk_start_offset + victim.chunk_length // 2  # in the middle of a chunk
    data = full.read_bytes()[:cut]
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(data)

    with pytest.raises(DataFormatError, match="rig recover"):
        read_trial(bad)
    fixed = tmp_path / "fixed.mcap"
    res = recover(bad, fixed)
    assert res["error"] and not res["complete_before"]
    raw = read_trial(fixed, "raw")
    ref = concat(blocks)
    n = len(raw)
    assert 0 < n < 20000 and n % 100 == 0
    assert np.array_equal(raw.friction_N, ref["friction_N"][:n])  # the complete chunks, intact
    assert raw.metadata["recovered"] == "true"
    assert raw.metadata["lubricant"] == "boundary"  # the original metadata kept
    info = trial_info(fixed)
    assert info["recovered"] and info["complete"]
    assert info["metadata"]["recovery"]["recovered_from"] == str(bad)
    assert info["attachments"][0]["name"] == "recipe.yaml"
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left


def test_recover_refuses_garbage(tmp_path):
    p = tmp_path / "g.mcap"
    p.write_bytes(b"not an mcap at all")
    with pytest.raises(DataFormatError):
        recover(p, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


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
    kinds = [e["kind"] for e in read_trial(path).events]
    assert kinds == ["log_start", "b", "a", "log_end"]


def test_flush_at_least_every_second_of_wall_time(tmp_path, monkeypatch):
    import rig.log as log_mod

    clock = [1000.0]
    monkeypatch.setattr(log_mod.time, "monotonic", lambda: clock[0])
    blocks = make_blocks(6)

    def raw_on_disk(path):
        return next(c["messages"] for c in trial_info(path)["channels"] if c["topic"] == RAW_TOPIC)

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
