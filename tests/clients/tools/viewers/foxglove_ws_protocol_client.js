// A Foxglove WebSocket client built on Foxglove's own protocol library (@foxglove/ws-protocol's
// FoxgloveClient, the client side of the protocol Foxglove publishes; package.json beside this
// file pins it) over node's built-in WebSocket (run with --experimental-websocket on node 20).
// Not pd-service's code: the tests use it as an independent client of pd-viz.
//
//   node --experimental-websocket foxglove_ws_protocol_client.js URL TOPIC...
//
// Offers the subprotocols "foxglove.sdk.v1" (foxglove-sdk's name) and FoxgloveClient's
// "foxglove.websocket.v1". Subscribes to each TOPIC as soon as it is advertised. Writes one
// JSON object per line on stdout: {"op": "open", "protocol"}, {"op": "serverInfo", ...},
// {"op": "advertise", "channel"}, {"op": "subscribed", "topic"}, {"op": "message", "topic",
// "log_ns" (a decimal string), "data" (base64)}, {"op": "status", "level", "message"} (the
// server's status messages, e.g. a refused subscription), {"op": "error", "error"},
// {"op": "close"}.
// Closing stdin closes the connection; the process then exits.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");

const [url, ...topics] = process.argv.slice(2);
const emit = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const ws = new WebSocket(url, ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const topicOfSub = new Map();
const subscribed = new Set();

client.on("open", () => emit({ op: "open", protocol: ws.protocol }));
client.on("serverInfo", (info) => emit(info));
client.on("advertise", (channels) => {
  for (const ch of channels) {
    emit({ op: "advertise", channel: ch });
    if (topics.includes(ch.topic) && !subscribed.has(ch.topic)) {
      subscribed.add(ch.topic);
      topicOfSub.set(client.subscribe(ch.id), ch.topic);
      emit({ op: "subscribed", topic: ch.topic });
    }
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
  emit({ op: "message", topic: topicOfSub.get(subscriptionId), log_ns: timestamp.toString(),
         data: bytes.toString("base64") });
});
client.on("status", ({ level, message }) => emit({ op: "status", level, message }));
client.on("error", (e) => emit({ op: "error", error: String(e && e.message ? e.message : e) }));
client.on("close", () => {
  emit({ op: "close" });
  process.exit(0);
});
process.stdin.on("end", () => client.close());
process.stdin.resume();
