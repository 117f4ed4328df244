// Independent validation of a trial log with the TypeScript MCAP library (@mcap/core, @mcap/support):
// the stream reader checks every chunk CRC and the data section; the indexed reader reads through the
// summary (chunk and message indexes) with CRCs checked, and its counts must match the statistics.
// Usage: NODE_PATH=<dir with node_modules> node validate_mcap.js FILE.mcap ...   -> one JSON line per file
const fs = require("fs");
const { McapStreamReader, McapIndexedReader } = require("@mcap/core");
const { loadDecompressHandlers } = require("@mcap/support");

async function validate(path, decompressHandlers) {
  const bytes = fs.readFileSync(path);
  const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  stream.append(new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength));
  const channels = new Map();
  const streamCounts = {};
  let footer = false;
  for (let rec; (rec = stream.nextRecord()); ) {
    if (rec.type === "Channel") channels.set(rec.id, rec.topic);
    if (rec.type === "Message") {
      const t = channels.get(rec.channelId);
      streamCounts[t] = (streamCounts[t] || 0) + 1;
    }
    if (rec.type === "Footer") footer = true;
  }
  const readable = {
    size: async () => BigInt(bytes.byteLength),
    read: async (offset, size) => new Uint8Array(bytes.buffer, bytes.byteOffset + Number(offset), Number(size)),
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  const indexedCounts = {};
  let n = 0;
  for await (const m of reader.readMessages({ validateCrcs: true })) {
    const t = reader.channelsById.get(m.channelId).topic;
    indexedCounts[t] = (indexedCounts[t] || 0) + 1;
    n++;
  }
  const stats = reader.statistics;
  return { path, footer, done: stream.done(), streamCounts, indexedCounts,
           statisticsMessageCount: stats ? Number(stats.messageCount) : null, indexedMessages: n,
           chunks: reader.chunkIndexes.length };
}

const sorted = (o) => JSON.stringify(Object.keys(o).sort().map((k) => [k, o[k]]));

(async () => {
  const decompressHandlers = await loadDecompressHandlers();
  let bad = 0;
  for (const path of process.argv.slice(2)) {
    try {
      const r = await validate(path, decompressHandlers);
      r.ok = r.footer && r.done && r.statisticsMessageCount === r.indexedMessages &&
        sorted(r.streamCounts) === sorted(r.indexedCounts);
      if (!r.ok) bad++;
      console.log(JSON.stringify(r));
    } catch (e) {
      bad++;
      console.log(JSON.stringify({ path, ok: false, error: String(e) }));
    }
  }
  process.exit(bad ? 1 : 0);
})();
