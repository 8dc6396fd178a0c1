// Subscribes to a Foxglove WebSocket server with @foxglove/ws-protocol (the client Foxglove's
// own tools use) and decodes CDR with @foxglove/rosmsg2-serialization. Prints one JSON object
// with the advertised channels, N decoded /joint_states and the /robot_description length.
import wsProtocol from "@foxglove/ws-protocol"; // a CommonJS package

import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, countArg] = process.argv.slice(2);
const want = Number(countArg ?? 5);
const out = { channels: {}, jointStates: [], robotDescription: null };
const subs = new Map(); // subscription id -> { topic, reader }
const client = new FoxgloveClient({
  // foxglove-sdk servers speak the same protocol under the name "foxglove.sdk.v1"; offer both
  ws: new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"]),
});
const timer = setTimeout(() => finish(2, "timeout"), 60000);

function finish(code, why) {
  clearTimeout(timer);
  if (why) out.error = why;
  console.log(JSON.stringify(out));
  client.close();
  process.exit(code);
}

client.on("error", (err) => finish(3, String(err?.message ?? err)));
client.on("serverInfo", (info) => { out.serverInfo = { name: info.name, capabilities: info.capabilities }; });
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.channels[ch.topic] = { schemaName: ch.schemaName, encoding: ch.encoding, schemaEncoding: ch.schemaEncoding };
    if (ch.topic === "/joint_states" || ch.topic === "/robot_description") {
      const reader = new MessageReader(parse(ch.schema, { ros2: true }));
      subs.set(client.subscribe(ch.id), { topic: ch.topic, reader });
    }
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const sub = subs.get(subscriptionId);
  if (!sub) return;
  const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  const msg = sub.reader.readMessage(bytes);
  if (sub.topic === "/joint_states") {
    out.jointStates.push({ name: msg.name, position: Array.from(msg.position) });
  } else {
    out.robotDescription = msg.data.length;
  }
  if (out.jointStates.length >= want && out.robotDescription !== null) finish(0);
});
