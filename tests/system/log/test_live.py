"""Live view (`rig run --live`, rig.log.live): a real WebSocket client speaking the Foxglove protocol
receives the running trial's samples, events and loop statistics, the same as the MCAP holds;
--pace paces the simulated rig without changing its data; a slow client never holds up the log."""

from __future__ import annotations

import asyncio
import json
import queue
import re
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from typer.testing import CliRunner

from rig.cli import app
from rig.config.profile import load_profile
from rig.config.recipe import compile_recipe, load_recipe
from rig.log import EVENTS_TOPIC, LOG25_TOPIC, STATS_TOPIC, TrialLogWriter
from rig.log.live import LiveView
from rig.session.sim import SimBackend

websockets = pytest.importorskip("websockets")
from websockets.asyncio.client import connect  # noqa: E402

# foxglove-sdk >= 0.x names the protocol "foxglove.sdk.v1": the same messages as foxglove.websocket.v1
# under a new name (its server refuses the old name); the client offers both.
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
TOPICS = (LOG25_TOPIC, EVENTS_TOPIC, STATS_TOPIC)


async def _collect(url: str, deadline_s: float, read: bool = True) -> dict:
    """Connect, subscribe to the rig's topics when advertised, gather message data until the server closes.

    Returns {"advertised": {topic: channel}, "messages": {topic: [(log_time_ns, dict), ...]}}.
    With ``read=False`` the client subscribes and then stops reading (a stalled viewer)."""
    got = {"advertised": {}, "messages": {t: [] for t in TOPICS}, "server_info": None}
    sub_topic: dict[int, str] = {}
    async with connect(url, subprotocols=SUBPROTOCOLS, open_timeout=60, max_size=None) as ws:
        assert ws.subprotocol in SUBPROTOCOLS
        loop = asyncio.get_running_loop()
        end = loop.time() + deadline_s
        while True:
            left = end - loop.time()
            if left <= 0:
                raise TimeoutError("the live server did not finish within the deadline")
            try:
                frame = await asyncio.wait_for(ws.recv(), left)
            except websockets.ConnectionClosed:
                break
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "serverInfo":
                    got["server_info"] = op
                elif op["op"] == "advertise":
                    subs = []
                    for ch in op["channels"]:
                        got["advertised"][ch["topic"]] = ch
                        if ch["topic"] in TOPICS:
                            sid = len(sub_topic) + 1
                            sub_topic[sid] = ch["topic"]
                            subs.append({"id": sid, "channelId": ch["id"]})
                    if subs:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                        if not read:
                            await asyncio.sleep(deadline_s)  # never read again
                            return got
                continue
            # binary: opcode 0x01 message data = u8 op, u32 subscription id, u64 log_time ns, payload
            assert frame[0] == 0x01, f"unexpected binary opcode {frame[0]}"
            sid, log_time = struct.unpack_from("<IQ", frame, 1)
            got["messages"][sub_topic[sid]].append((log_time, json.loads(frame[13:])))
    return got


def _mcap_messages(path) -> dict:
    out = {t: {} for t in TOPICS}
    with open(path, "rb") as fh:
        for _schema, channel, msg in make_reader(fh).iter_messages(topics=list(TOPICS)):
            out[channel.topic].setdefault(msg.log_time, []).append(json.loads(msg.data))
    return out


def _start_rig_run(args: list[str]) -> tuple[subprocess.Popen, str, list[str]]:
    """Start `rig run ...` and wait for the line naming the live view's URL (stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "run", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lines: queue.Queue = queue.Queue()
    err: list[str] = []

    def pump():
        for line in proc.stderr:
            err.append(line)
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    end = time.monotonic() + 240
    while time.monotonic() < end:
        try:
            line = lines.get(timeout=max(0.1, end - time.monotonic()))
        except queue.Empty:
            break
        if line is None:
            break
        m = re.search(r"live view: (ws://[\d.]+:\d+)", line)
        if m:
            return proc, m.group(1), err
    proc.kill()
    raise AssertionError(f"`rig run --live` did not announce its URL; stderr:\n{''.join(err)}")


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_live_run_streams_what_the_log_holds(repo_root, tmp_path):
    out = tmp_path / "live.mcap"
    recipe = repo_root / "config" / "recipes" / "smoke.yaml"  # 22.6 s of trial, about 11 s at --pace 2
    proc, url, err = _start_rig_run([str(recipe), "--sim", "--live", "--live-port", "0", "--pace", "2", "-q",
                                     "-o", str(out)])
    assert url.startswith("ws://127.0.0.1:"), url  # loopback unless told otherwise
    try:
        got = asyncio.run(_collect(url, deadline_s=300))
    finally:
        try:
            proc.wait(timeout=300)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert proc.returncode == 0, "".join(err)

    # the channels: the log's topics, JSON with the log's JSON schemas (the layout works live)
    adv = got["advertised"]
    assert set(TOPICS) <= set(adv), adv.keys()
    assert adv[LOG25_TOPIC]["encoding"] == "json" and adv[LOG25_TOPIC]["schemaEncoding"] == "jsonschema"
    assert adv[LOG25_TOPIC]["schemaName"] == "rig.Sample"
    props = json.loads(adv[LOG25_TOPIC]["schema"])["properties"]
    for f in ("t_s", "position_um", "position_ref_um", "friction_N", "mu", "normal_1_N", "normal_2_N",
              "valve_cmd"):
        assert f in props

    logged = _mcap_messages(out)
    # samples: a gap-free run of the 25 Hz channel, each equal to the logged one at the same log_time
    samples = got["messages"][LOG25_TOPIC]
    assert len(samples) >= 25, f"only {len(samples)} samples received"
    t = np.array([m["t_s"] for _, m in samples])
    # 25 Hz block means stamped at their interval's centre; the last, partial interval (written when
    # the log closes) at its own centre, less than 0.04 s after the one before
    assert np.allclose(np.diff(t[:-1]), 0.04, atol=1e-9), "samples missing or out of order"
    assert 0 < t[-1] - t[-2] <= 0.04 + 1e-9
    assert t[-1] > 20.0  # up to the end of the 22.6 s trial
    for log_time, m in samples:
        assert log_time in logged[LOG25_TOPIC], f"live sample at t={m['t_s']} s has no logged twin"
        ref = logged[LOG25_TOPIC][log_time][0]
        assert set(m) == set(ref)
        for k, v in m.items():
            # the log prints the 25 Hz means with two decimals beyond each device's count step
            # (rig.log.writer); the live view sends them unrounded
            assert v == pytest.approx(ref[k], rel=1e-5, abs=1e-5), (k, v, ref[k])

    # events: the end of the trial at least, each one the log holds at the same log_time
    events = got["messages"][EVENTS_TOPIC]
    kinds = [m["kind"] for _, m in events]
    assert "log_end" in kinds and "stop_state" in kinds, kinds
    for log_time, m in events:
        assert m in logged[EVENTS_TOPIC].get(log_time, []), m

    # loop statistics, once a trial second
    stats = got["messages"][STATS_TOPIC]
    assert stats, "no loop statistics received"
    for log_time, m in stats:
        assert m in logged[STATS_TOPIC].get(log_time, []), m


def test_sim_pace_waits_and_keeps_the_data(repo_root):
    """--pace 4: the trial takes at least duration / 4 of wall time; the samples are those of an unpaced run."""
    profile = load_profile(repo_root / "config" / "rigs" / "sim.yaml")
    recipe = load_recipe(repo_root / "config" / "recipes" / "smoke.yaml")
    plan = compile_recipe(recipe, profile)
    fm = profile.friction_model(recipe.lubricant)

    def run(pace):
        b = SimBackend(profile, fm, recipe.normal_force_N, 7, block_ticks=1000, pace=pace)
        b.start(plan)
        t0 = time.monotonic()
        blocks = []
        while (blk := b.receive()) is not None:
            blocks.append(blk.data["position_um"].copy())
        return time.monotonic() - t0, blocks

    wall_fast, fast = run(0.0)
    wall_paced, paced = run(4.0)
    assert wall_paced >= plan.duration_s / 4 * 0.95
    assert max(b.size for b in paced) == 400  # blocks of 0.1 s of wall time: 0.4 s of trial at 4x
    np.testing.assert_array_equal(np.concatenate(fast), np.concatenate(paced))
    with pytest.raises(ValueError, match="pace"):
        SimBackend(profile, fm, 100.0, 7, pace=-1)


def test_a_stalled_viewer_does_not_hold_up_the_log(tmp_path):
    """A client that subscribes and never reads again: the writer goes on at full speed, the server drops."""
    view = LiveView("127.0.0.1", 0, backlog=64)
    result: dict = {}
    client = threading.Thread(target=lambda: result.update(
        asyncio.run(_collect(view.url, deadline_s=30, read=False))), daemon=True)
    client.start()
    # wait for the subscription (the server has a sink on /log25)
    end = time.monotonic() + 120
    while not view._chan[LOG25_TOPIC].has_sinks() and time.monotonic() < end:
        time.sleep(0.05)
    assert view._chan[LOG25_TOPIC].has_sinks(), "the client did not subscribe"
    w = TrialLogWriter(tmp_path / "x.mcap", fsync=False)
    view.attach(w)
    n = 1000
    t_start = time.monotonic()
    for k in range(600):  # 600 s of 1 kHz data: 15,000 samples to a viewer that does not read
        t = (k * n + np.arange(n)) / 1000.0
        w.write_block({"t_s": t, "position_um": np.sin(t), "position_ref_um": np.sin(t), "friction_N": np.cos(t),
                       "normal_1_N": np.full(n, 50.0), "normal_2_N": np.full(n, 50.0), "valve_cmd": 0 * t})
        w.event(float(t[-1]), "marker", k=k)
    w.close()
    elapsed = time.monotonic() - t_start
    view.close(linger_s=0)
    assert not w.listener_errors
    assert view.published[LOG25_TOPIC] + 25 * view.dropped >= 15000 - 25  # every sample handed over or counted
    assert elapsed < 120  # it finished: nothing waited for the client (generous: a loaded machine)


def test_live_options_bad_input(repo_root, tmp_path):
    recipe = str(repo_root / "config" / "recipes" / "smoke.yaml")
    res = CliRunner().invoke(app, ["run", recipe, "--sim", "--pace", "-1", "-o", str(tmp_path / "a.mcap")])
    assert res.exit_code == 2 and "--pace" in res.output
    res = CliRunner().invoke(app, ["run", recipe, "--hardware", str(repo_root / "config/rigs/emulated.yaml"),
                                   "--pace", "10", "-o", str(tmp_path / "b.mcap")])
    assert res.exit_code == 2 and "real time" in res.output
    with socket.socket() as s:  # the port is taken: one clear error, nothing run
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        res = CliRunner().invoke(app, ["run", recipe, "--sim", "--live", "--live-port", str(port), "-q",
                                       "-o", str(tmp_path / "c.mcap")])
    assert res.exit_code == 1, res.output
    assert f"127.0.0.1:{port}" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "c.mcap").exists()
