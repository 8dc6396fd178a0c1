// Subscribes to every channel a Foxglove WebSocket server advertises, as Foxglove does (on the
// advertisement, including channels advertised later), with @foxglove/ws-protocol, and counts
// the messages per topic. Prints "ready" on stderr once a /joint_states message arrived (the
// subscriptions are in place), then one JSON object on stdout once every topic named on the
// command line got a message, or after the timeout (s).
import wsProtocol from "@foxglove/ws-protocol"; // a CommonJS package

import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, timeoutArg, ...want] = process.argv.slice(2);
const out = { advertised: [], counts: {} };
const subs = new Map(); // subscription id -> topic
let ready = false;
const client = new FoxgloveClient({
  ws: new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"]),
});
const timer = setTimeout(() => finish(2, "timeout"), Number(timeoutArg ?? 60) * 1000);

function finish(code, why) {
  clearTimeout(timer);
  if (why) out.error = why;
  console.log(JSON.stringify(out));
  client.close();
  process.exit(code);
}

client.on("error", (err) => finish(3, String(err?.message ?? err)));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.advertised.push(ch.topic);
    subs.set(client.subscribe(ch.id), ch.topic);
  }
});
client.on("message", ({ subscriptionId }) => {
  const topic = subs.get(subscriptionId);
  out.counts[topic] = (out.counts[topic] ?? 0) + 1;
  if (!ready && topic === "/joint_states") {
    ready = true;
    process.stderr.write("ready\n");
  }
  if (ready && want.length && want.every((t) => out.counts[t] > 0)) finish(0);
});
