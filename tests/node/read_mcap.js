#!/usr/bin/env node
// Open MCAP files as Foxglove and Lichtblick do: @mcap/core's indexed reader (the summary,
// the chunk indexes, each chunk's message indexes) and every message decoded from its
// channel's own ros2msg schema by @foxglove/rosmsg2-serialization. Prints one JSON line per
// file: messages per topic; exits 1 on any failure (tests/node/setup.sh installs the
// packages; cli/tests/journal.rs runs it).
"use strict";
const fs = require("node:fs/promises");
const { McapIndexedReader } = require("@mcap/core");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");

async function readFile(path) {
  const fh = await fs.open(path, "r");
  try {
    const size = BigInt((await fh.stat()).size);
    const readable = {
      size: async () => size,
      read: async (offset, length) => {
        const buf = Buffer.alloc(Number(length));
        await fh.read(buf, 0, Number(length), Number(offset));
        return new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
      },
    };
    const reader = await McapIndexedReader.Initialize({ readable });
    const decoders = new Map();
    const counts = {};
    let total = 0;
    for await (const msg of reader.readMessages()) {
      const channel = reader.channelsById.get(msg.channelId);
      const schema = reader.schemasById.get(channel.schemaId);
      if (schema.encoding !== "ros2msg" || channel.messageEncoding !== "cdr") {
        throw new Error(`${channel.topic}: ${schema.encoding}/${channel.messageEncoding}`);
      }
      let decoder = decoders.get(schema.id);
      if (!decoder) {
        const text = new TextDecoder().decode(schema.data);
        decoder = new MessageReader(parse(text, { ros2: true }));
        decoders.set(schema.id, decoder);
      }
      const decoded = decoder.readMessage(msg.data);
      if (decoded == null || typeof decoded !== "object") {
        throw new Error(`${channel.topic}: nothing decoded`);
      }
      counts[channel.topic] = (counts[channel.topic] ?? 0) + 1;
      total += 1;
    }
    const summary = Number(reader.statistics?.messageCount ?? -1);
    return { file: path, foxglove: counts, messages: total, agree: total === summary };
  } finally {
    await fh.close();
  }
}

(async () => {
  let ok = true;
  for (const path of process.argv.slice(2)) {
    try {
      const r = await readFile(path);
      ok = ok && r.agree;
      console.log(JSON.stringify(r));
    } catch (e) {
      ok = false;
      console.log(JSON.stringify({ file: path, error: String(e && e.message ? e.message : e) }));
    }
  }
  process.exit(ok ? 0 : 1);
})();
