"""Recovery: rewrite a truncated or damaged trial log into a complete, verified one."""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

from mcap.writer import CompressionType, Writer

from rig import __version__
from rig.data import DataFormatError, atomic_path
from rig.log.reader import scan
from rig.log.schemas import MCAP_PROFILE


def recover(path_in: str | os.PathLike, path_out: str | os.PathLike, *, overwrite: bool = True) -> dict:
    """Rewrite a truncated/damaged trial log (no footer, or chunks failing their CRC) into a readable one.

    Keeps every intact chunk and record up to where the file's framing ends; a
    chunk whose CRC does not match is left out (its values are never carried
    forward). The new file is written atomically, with a ``recovery`` metadata
    record (source, error, corrupt chunks, counts) and a ``trial_end`` record
    with status ``recovered`` when the original had none. Returns a summary dict.
    """
    path_in, path_out = Path(path_in), Path(path_out)
    if path_out.exists() and path_in.exists() and path_in.resolve() == path_out.resolve():
        raise ValueError("recover writes a new file: --out must differ from the input")
    c = scan(path_in)
    if not c.channels:
        raise DataFormatError(path_in, None, f"nothing recoverable: no intact chunk before the damage "
                                             f"({c.error or 'empty'})")
    records = c.metadata_dict()
    t0 = c.start_time_ns
    counts: dict[str, int] = {}
    last_t = 0.0
    with atomic_path(path_out, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile=(c.header.profile if c.header else MCAP_PROFILE), library=f"rig {__version__} (recover)")
        sid_map = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(c.schemas.items())}
        cid_map = {cid: w.register_channel(chn.topic, chn.message_encoding, sid_map.get(chn.schema_id, 0),
                                           dict(chn.metadata))
                   for cid, chn in sorted(c.channels.items())}
        for m in c.messages:
            if m.channel_id not in cid_map:
                continue
            w.add_message(cid_map[m.channel_id], log_time=m.log_time, data=m.data,
                          publish_time=m.publish_time, sequence=m.sequence)
            topic = c.topic_of(m)
            counts[topic] = counts.get(topic, 0) + 1
            last_t = max(last_t, (m.log_time - t0) / 1e9)
        for md in c.metadata:
            w.add_metadata(md.name, dict(md.metadata))
        for a in c.attachments:
            w.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                             media_type=a.media_type, data=a.data)
        problems = []
        if c.error or not c.complete:
            problems.append(c.error or "no footer")
        if c.damage:
            problems.append(f"{len(c.damage)} corrupt chunk(s) dropped: {c.damage_text()}")
        info = {"recovered": "true", "recovered_from": str(path_in),
                "recovery_error": "; ".join(problems) or "none",
                "original_complete": str(bool(c.complete and not c.error and not c.damage)).lower(),
                "corrupt_chunks": str(len(c.damage)),
                "messages": str(sum(counts.values())),
                "recovered_utc": _dt.datetime.now(_dt.timezone.utc).isoformat()}
        info.update({f"messages{t.replace('/', '_')}": str(n) for t, n in counts.items()})
        w.add_metadata("recovery", info)
        if "trial_end" not in records:
            w.add_metadata("trial_end", {"status": "recovered", "duration_s": repr(last_t)})
        w.finish()
    return {"messages": counts, "error": c.error, "damage": c.damage,
            "complete_before": c.complete and not c.error and not c.damage, "last_t_s": last_t,
            "path": str(path_out)}
