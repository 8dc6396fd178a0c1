// Reads an MCAP file with @mcap/core (indexed, or --stream for a file cut short) and decodes
// every ROS 2 message with @foxglove/rosmsg + @foxglove/rosmsg2-serialization: code nobody in
// ucr wrote. Prints one JSON object: schemas per topic, message counts, last /joint_states.
import { open, readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers } from "@mcap/support";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";

const [file, mode] = process.argv.slice(2);
const decompressHandlers = await loadDecompressHandlers();
const schemas = new Map(); // id -> schema
const channels = new Map(); // id -> channel
const readers = new Map(); // schema id -> MessageReader
const out = { mode: mode ?? "indexed", topics: {}, counts: {}, decoded: 0, last: {} };

function readerFor(schemaId) {
  let r = readers.get(schemaId);
  if (!r) {
    const s = schemas.get(schemaId);
    const text = new TextDecoder().decode(s.data);
    r = new MessageReader(parse(text, { ros2: true }));
    readers.set(schemaId, r);
  }
  return r;
}

function onMessage(msg) {
  const ch = channels.get(msg.channelId);
  const value = readerFor(ch.schemaId).readMessage(msg.data);
  out.decoded += 1;
  out.counts[ch.topic] = (out.counts[ch.topic] ?? 0) + 1;
  if (ch.topic === "/joint_states") {
    out.last[ch.topic] = { name: value.name, position: Array.from(value.position) };
  }
}

function noteChannel(ch) {
  channels.set(ch.id, ch);
  const s = schemas.get(ch.schemaId);
  out.topics[ch.topic] = { schema: s.name, encoding: s.encoding, messageEncoding: ch.messageEncoding };
}

if (out.mode === "--stream") {
  const reader = new McapStreamReader({ decompressHandlers });
  reader.append(await readFile(file));
  for (;;) {
    let rec;
    try {
      rec = reader.nextRecord();
    } catch (err) {
      out.error = String(err);
      break;
    }
    if (rec === undefined) break; // needs more bytes: the file ends here
    if (rec.type === "Schema") schemas.set(rec.id, rec);
    else if (rec.type === "Channel") noteChannel(rec);
    else if (rec.type === "Message") onMessage(rec);
  }
  out.complete = reader.done();
} else {
  const handle = await open(file, "r");
  const reader = await McapIndexedReader.Initialize({
    readable: new FileHandleReadable(handle),
    decompressHandlers,
  });
  for (const [id, s] of reader.schemasById) schemas.set(id, s);
  for (const ch of reader.channelsById.values()) noteChannel(ch);
  for await (const msg of reader.readMessages()) onMessage(msg);
  out.statistics = Number(reader.statistics?.messageCount ?? -1);
  await handle.close();
}
console.log(JSON.stringify(out));
