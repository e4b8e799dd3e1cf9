// Reads a flight recording with @mcap/core, the MCAP library of Foxglove
// (installed by npm ci from this directory's lockfile; NODE_PATH names its
// node_modules), as a check of our own writer (formats/mcap/mcap.cc):
//
//   node read_mcap.js FILE
//
// - McapIndexedReader: the footer, the summary and its CRC, the statistics;
// - McapStreamReader with CRC validation: every record from the start, in
//   order.
// Prints one JSON object: the header, the schemas, and per topic the message
// count, the first and last log times, and a SHA-256 over the messages'
// data in order (each prefixed by its length as a little-endian uint32), so
// that a test can compare what a replay published with what was recorded.
// Exits 1 with the reader's error when the file is not valid.

"use strict";

const crypto = require("crypto");
const fs = require("fs");
const { McapIndexedReader, McapStreamReader } = require("@mcap/core");

async function indexed(path) {
  const handle = await fs.promises.open(path, "r");
  try {
    const size = (await handle.stat()).size;
    const readable = {
      size: async () => BigInt(size),
      read: async (offset, length) => {
        const buffer = Buffer.alloc(Number(length));
        await handle.read(buffer, 0, Number(length), Number(offset));
        return new Uint8Array(buffer.buffer, buffer.byteOffset, buffer.byteLength);
      },
    };
    const reader = await McapIndexedReader.Initialize({ readable });
    return {
      statistics: {
        message_count: Number(reader.statistics.messageCount),
        schema_count: reader.statistics.schemaCount,
        channel_count: reader.statistics.channelCount,
      },
      channels: [...reader.channelsById.values()].map((c) => c.topic).sort(),
    };
  } finally {
    await handle.close();
  }
}

function streamed(path) {
  const reader = new McapStreamReader({ validateCrcs: true });
  reader.append(new Uint8Array(fs.readFileSync(path)));
  const schemas = new Map();
  const channels = new Map();
  const topics = {};
  const digests = new Map();
  let header = null;
  let footer = false;
  for (let record; (record = reader.nextRecord()); ) {
    switch (record.type) {
      case "Header":
        header = { profile: record.profile, library: record.library };
        break;
      case "Schema":
        schemas.set(record.id, {
          name: record.name, encoding: record.encoding, bytes: record.data.length,
        });
        break;
      case "Channel":
        channels.set(record.id, record);
        break;
      case "Message": {
        const channel = channels.get(record.channelId);
        const topic = channel.topic;
        if (!topics[topic]) {
          topics[topic] = {
            count: 0,
            schema: schemas.get(channel.schemaId).name,
            encoding: channel.messageEncoding,
            first_log_time_ns: record.logTime.toString(),
          };
          digests.set(topic, crypto.createHash("sha256"));
        }
        const length = Buffer.alloc(4);
        length.writeUInt32LE(record.data.length);
        digests.get(topic).update(length);
        digests.get(topic).update(record.data);
        topics[topic].count += 1;
        topics[topic].last_log_time_ns = record.logTime.toString();
        break;
      }
      case "Footer":
        footer = true;
        break;
      default:
        break;
    }
  }
  if (!reader.done()) throw new Error("the stream reader did not reach the end of the file");
  for (const [topic, hash] of digests) topics[topic].sha256 = hash.digest("hex");
  return { header, footer, schemas: [...schemas.values()], topics };
}

async function main() {
  const path = process.argv[2];
  const result = { ...streamed(path), ...(await indexed(path)) };
  process.stdout.write(JSON.stringify(result) + "\n");
}

main().catch((error) => {
  process.stderr.write(`read_mcap.js: ${error.stack || error}\n`);
  process.exit(1);
});
