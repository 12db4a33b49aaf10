// Reads an MCAP file with Foxglove's TypeScript MCAP library (@mcap/core, the reader inside
// Foxglove Studio and Lichtblick), independently of the Python `mcap` package that wrote it.
//
//   node check_mcap.mjs FILE.mcap            -> one JSON object on stdout
//   node check_mcap.mjs --foxglove-schema N  -> Foxglove's JSON schema N (e.g. CompressedImage)
//
// Checks made here (each failure is listed in "errors", never thrown past main):
// * stream: the whole file front to back with McapStreamReader (chunk CRCs validated, the
//   zstd chunks decompressed with @mcap/support's handlers); "done" is true only when the
//   footer was reached;
// * indexed: McapIndexedReader (the path Studio takes for a complete file: summary CRC,
//   chunk and message indexes, channels and schemas from the summary), every message read
//   with CRC validation; the data section CRC recomputed over the bytes before DataEnd;
// * per channel: topic, message encoding, schema name and encoding, message count, and
//   for "json" channels how many payloads do not parse as a JSON object.
// The Python test compares all this with what the recorder meant to write.
import { readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { loadDecompressHandlers } from "@mcap/support";
import { crc32 } from "@foxglove/crc";
import * as foxgloveSchemas from "@foxglove/schemas/jsonschema.js";

function bufferReadable(bytes) {
  return {
    size: async () => BigInt(bytes.byteLength),
    read: async (offset, length) => {
      const start = Number(offset), end = start + Number(length);
      if (end > bytes.byteLength) throw new Error(`read past the end (${end} > ${bytes.byteLength})`);
      return bytes.subarray(start, end);
    },
  };
}

function channelEntry(table, channel, schema) {
  let entry = table.get(channel.topic);
  if (!entry) {
    entry = {
      topic: channel.topic, messageEncoding: channel.messageEncoding,
      schemaName: schema ? schema.name : null, schemaEncoding: schema ? schema.encoding : null,
      schemaData: schema && schema.encoding === "jsonschema"
        ? JSON.parse(new TextDecoder().decode(schema.data)) : null,
      count: 0, jsonErrors: 0, firstJson: null,
    };
    table.set(channel.topic, entry);
  }
  return entry;
}

function countMessage(entry, data) {
  entry.count++;
  if (entry.messageEncoding !== "json") return;
  try {
    const obj = JSON.parse(new TextDecoder().decode(data));
    if (typeof obj !== "object" || obj === null || Array.isArray(obj)) entry.jsonErrors++;
    else if (entry.firstJson === null) entry.firstJson = obj;
  } catch {
    entry.jsonErrors++;
  }
}

async function streamRead(bytes, decompressHandlers) {
  const out = { records: 0, messages: 0, chunks: 0, metadata: [], done: false, error: null,
                profile: null, library: null };
  const reader = new McapStreamReader({ decompressHandlers, validateCrcs: true,
                                        includeChunks: true });
  reader.append(bytes);
  try {
    for (let rec; (rec = reader.nextRecord()); ) {
      out.records++;
      if (rec.type === "Header") { out.profile = rec.profile; out.library = rec.library; }
      else if (rec.type === "Message") out.messages++;
      else if (rec.type === "Chunk") out.chunks++;
      else if (rec.type === "Metadata") out.metadata.push(rec.name);
    }
    out.done = reader.done();
  } catch (err) {
    out.error = String(err && err.message ? err.message : err);
  }
  return out;
}

async function indexedRead(bytes, decompressHandlers) {
  const out = { messages: 0, channels: [], metadata: [], dataSectionCrc: null, error: null };
  try {
    const reader = await McapIndexedReader.Initialize({ readable: bufferReadable(bytes),
                                                        decompressHandlers });
    const table = new Map();
    for await (const msg of reader.readMessages({ validateCrcs: true })) {
      const channel = reader.channelsById.get(msg.channelId);
      const schema = channel.schemaId ? reader.schemasById.get(channel.schemaId) : undefined;
      countMessage(channelEntry(table, channel, schema), msg.data);
      out.messages++;
    }
    for await (const md of reader.readMetadata()) out.metadata.push(md.name);
    out.channels = [...table.values()];
    out.statisticsMessageCount = reader.statistics ? Number(reader.statistics.messageCount) : null;
    if (reader.dataSectionCrc !== undefined) {
      const computed = crc32(bytes.subarray(0, Number(reader.dataEndOffset)));
      out.dataSectionCrc = { stored: reader.dataSectionCrc, computed };
    }
  } catch (err) {
    out.error = String(err && err.message ? err.message : err);
  }
  return out;
}

async function main(argv) {
  if (argv[0] === "--foxglove-schema") {
    const schema = foxgloveSchemas[argv[1]];
    if (!schema) throw new Error(`no Foxglove schema ${argv[1]}`);
    process.stdout.write(JSON.stringify(schema));
    return;
  }
  const bytes = new Uint8Array(await readFile(argv[0]));
  const decompressHandlers = await loadDecompressHandlers();
  const stream = await streamRead(bytes, decompressHandlers);
  const indexed = await indexedRead(bytes, decompressHandlers);
  process.stdout.write(JSON.stringify({ file: argv[0], size: bytes.byteLength, stream, indexed }));
}

main(process.argv.slice(2)).catch((err) => {
  process.stderr.write(`check_mcap: ${err && err.stack ? err.stack : err}\n`);
  process.exit(2);
});
