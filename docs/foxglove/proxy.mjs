// Foxglove Studio 1.48 asks for the protocol by its old name, `foxglove.websocket.v1`;
// the foxglove crate's server (muster view) speaks the same protocol as
// `foxglove.sdk.v1`. This passes frames both ways unchanged and renames the subprotocol.
// Usage: node proxy.mjs PORT ws://VIEW_ADDR (port 0: any free one); prints {"listen": PORT}.
import { WebSocketServer, WebSocket } from "ws";

const [port, upstream] = process.argv.slice(2);
const server = new WebSocketServer({
  port: Number(port),
  host: "127.0.0.1",
  handleProtocols: (offered) => (offered.has("foxglove.websocket.v1") ? "foxglove.websocket.v1" : false),
});
server.on("connection", (client) => {
  const up = new WebSocket(upstream, ["foxglove.sdk.v1"]);
  const early = [];
  up.on("open", () => early.splice(0).forEach((m) => up.send(m.data, { binary: m.binary })));
  up.on("message", (data, binary) => client.send(data, { binary }));
  client.on("message", (data, binary) => {
    if (up.readyState === WebSocket.OPEN) up.send(data, { binary });
    else early.push({ data, binary });
  });
  up.on("close", () => client.close());
  client.on("close", () => up.close());
  up.on("error", (e) => { console.error(`upstream: ${e}`); client.close(); });
});
server.on("listening", () => console.log(JSON.stringify({ listen: server.address().port })));
