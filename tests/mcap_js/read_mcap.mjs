// Independent reader for the trace tests: reads an MCAP file with Foxglove's TypeScript @mcap/core
// (zstd chunks decompressed by fzstd, pure JS) and prints one JSON document on stdout:
//
//   node read_mcap.mjs FILE.mcap
//
// {
//   "indexed": {                       // McapIndexedReader: footer, summary, chunk and message indexes
//     "library", "profile", "chunks",
//     "statistics": {"messageCount", "channelMessageCounts": {topic: n}},
//     "topics": {topic: {"schema", "schemaEncoding", "messageEncoding", "metadata", "count",
//                        "firstLogTime", "lastLogTime"}},
//     "json": {topic: [[logTime, publishTime, sequence, decodedMessage], ...]},  // JSON channels
//     "metadata": {name: {key: value}}
//   },
//   "stream": {                        // McapStreamReader: every record in file order, CRCs checked
//     "done": bool, "records": {opcode name: n}, "counts": {topic: n}, "logTimesSorted": bool
//   }
// }
//
// Times are decimal strings (they are 64-bit integers). Messages are decoded with JSON.parse.

import { readFile, open } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { decompress } from "fzstd";

const decompressHandlers = {
  zstd: (buffer, decompressedSize) => {
    const out = decompress(buffer);
    if (BigInt(out.byteLength) !== decompressedSize) {
      throw new Error(`zstd: ${out.byteLength} bytes, expected ${decompressedSize}`);
    }
    return out;
  },
};

const decoder = new TextDecoder();

async function indexed(path) {
  const handle = await open(path, "r");
  try {
    const readable = {
      size: async () => BigInt((await handle.stat()).size),
      read: async (offset, size) => {
        const buffer = new Uint8Array(Number(size));
        const { bytesRead } = await handle.read(buffer, 0, Number(size), Number(offset));
        if (bytesRead !== Number(size)) throw new Error(`short read at ${offset}`);
        return buffer;
      },
    };
    const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
    const topics = {};
    const json = {};
    for (const channel of reader.channelsById.values()) {
      const schema = reader.schemasById.get(channel.schemaId);
      topics[channel.topic] = {
        schema: schema?.name ?? "",
        schemaEncoding: schema?.encoding ?? "",
        messageEncoding: channel.messageEncoding,
        metadata: Object.fromEntries(channel.metadata),
        count: 0,
        firstLogTime: null,
        lastLogTime: null,
      };
      if (channel.messageEncoding === "json") json[channel.topic] = [];
    }
    for await (const message of reader.readMessages({ validateCrcs: true })) {
      const channel = reader.channelsById.get(message.channelId);
      const topic = topics[channel.topic];
      topic.count += 1;
      const logTime = message.logTime.toString();
      if (topic.firstLogTime === null) topic.firstLogTime = logTime;
      topic.lastLogTime = logTime;
      if (channel.messageEncoding === "json") {
        json[channel.topic].push([
          logTime,
          message.publishTime.toString(),
          message.sequence,
          JSON.parse(decoder.decode(message.data)),
        ]);
      }
    }
    const metadata = {};
    for await (const record of reader.readMetadata()) {
      metadata[record.name] = Object.fromEntries(record.metadata);
    }
    const channelMessageCounts = {};
    for (const [id, count] of reader.statistics?.channelMessageCounts ?? []) {
      channelMessageCounts[reader.channelsById.get(id).topic] = count.toString();
    }
    return {
      library: reader.header.library,
      profile: reader.header.profile,
      chunks: reader.chunkIndexes.length,
      statistics: {
        messageCount: reader.statistics?.messageCount.toString() ?? null,
        channelMessageCounts,
      },
      topics,
      json,
      metadata,
    };
  } finally {
    await handle.close();
  }
}

async function stream(path) {
  const reader = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  reader.append(await readFile(path));
  const records = {};
  const counts = {};
  const channels = new Map();
  let last = -1n;
  let sorted = true;
  for (let record; (record = reader.nextRecord()); ) {
    records[record.type] = (records[record.type] ?? 0) + 1;
    if (record.type === "Channel") channels.set(record.id, record.topic);
    if (record.type === "Message") {
      const topic = channels.get(record.channelId);
      counts[topic] = (counts[topic] ?? 0) + 1;
      if (record.logTime < last) sorted = false;
      last = record.logTime;
    }
  }
  return { done: reader.done(), records, counts, logTimesSorted: sorted };
}

const path = process.argv[2];
if (!path) {
  console.error("usage: node read_mcap.mjs FILE.mcap");
  process.exit(2);
}
const result = { stream: await stream(path) };
if (result.stream.done) result.indexed = await indexed(path);
process.stdout.write(JSON.stringify(result));
