// Connects to a Foxglove WebSocket server with @foxglove/ws-protocol's FoxgloveClient,
// subscribes to every channel it advertises, and after SECONDS prints one JSON object:
// the server's name, the channels (topic, encoding, schema name) and the messages
// received per topic. Usage: node client.mjs ws://HOST:PORT SECONDS
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, seconds] = process.argv.slice(2);
// The server speaks `foxglove.sdk.v1`, the same protocol as `foxglove.websocket.v1`
// under its new name; the client leaves the subprotocol to the socket.
const client = new FoxgloveClient({ ws: new WebSocket(url, ["foxglove.sdk.v1"]) });
const channels = new Map();
const topicOf = new Map();
const counts = {};
let server = null;
client.on("serverInfo", (info) => {
  server = info.name;
});
client.on("advertise", (chs) => {
  for (const ch of chs) {
    channels.set(ch.id, { topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName });
    topicOf.set(client.subscribe(ch.id), ch.topic);
  }
});
client.on("message", ({ subscriptionId }) => {
  const topic = topicOf.get(subscriptionId);
  counts[topic] = (counts[topic] ?? 0) + 1;
});
client.on("error", (e) => {
  console.error(`client error: ${e}`);
});
setTimeout(() => {
  console.log(JSON.stringify({ server, channels: [...channels.values()], counts }));
  client.close();
  process.exit(0);
}, Number(seconds) * 1000);
