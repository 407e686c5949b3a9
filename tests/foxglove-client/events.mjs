// Reads `muster view`'s event feed with the `ws` package: connects to URL, and after
// SECONDS prints one JSON object: whether it opened, the HTTP status if refused, and the
// records received (each parsed). Usage: node events.mjs ws://HOST:PORT/events?token=T SECONDS
import WebSocket from "ws";

const [url, seconds] = process.argv.slice(2);
const out = { opened: false, status: null, records: [] };
const ws = new WebSocket(url);
ws.on("open", () => {
  out.opened = true;
});
ws.on("unexpected-response", (_req, res) => {
  out.status = res.statusCode;
  ws.terminate();
});
ws.on("message", (data) => {
  out.records.push(JSON.parse(data.toString()));
});
ws.on("error", () => {});
setTimeout(() => {
  console.log(JSON.stringify(out));
  ws.terminate();
  process.exit(0);
}, Number(seconds) * 1000);
