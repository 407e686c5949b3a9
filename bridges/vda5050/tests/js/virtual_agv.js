// Virtual VDA 5050 vehicles from vda-5050-lib (AgvController + VirtualAgvAdapter), and a
// sniffer that checks every message on the interface against the library's VDA 5050
// 2.0 validators (generated from the official JSON schemas).
//
//   node virtual_agv.js --broker mqtt://127.0.0.1:PORT [--interface uagv]
//        [--manufacturer acme] [--count 1] [--speed 2] [--state-every-ms 30000]
//
// Prints one JSON object a line: {"event":"ready"}, {"event":"state",...} for every
// state a vehicle publishes, {"event":"invalid",...} for any message that fails its
// schema, and {"event":"checked",...} counts when told `stats` on standard input.
// Standard input also takes `offline SERIAL` (an orderly stop: OFFLINE), `online
// SERIAL` (started again), `raw TOPIC JSON` (publishes as is) and `exit` (the process
// ends without a word: the broker sends each vehicle's last will, CONNECTIONBROKEN).
"use strict";
const { AgvController, VirtualAgvAdapter } = require("vda-5050-lib");
const validators = require("vda-5050-lib/common/vda-5050-validators-2.0");
const mqtt = require("mqtt");
const readline = require("readline");

const args = {};
for (let i = 2; i < process.argv.length; i += 2) {
  args[process.argv[i].replace(/^--/, "")] = process.argv[i + 1];
}
const broker = args.broker;
const iface = args.interface || "uagv";
const manufacturer = args.manufacturer || "acme";
const count = parseInt(args.count || "1", 10);
const speed = parseFloat(args.speed || "2");
const stateEvery = parseInt(args["state-every-ms"] || "30000", 10);
const say = (o) => process.stdout.write(JSON.stringify(o) + "\n");

const check = {
  connection: validators.validateConnection,
  state: validators.validateState,
  order: validators.validateOrder,
  instantActions: validators.validateInstantActions,
  visualization: validators.validateVisualization,
  factsheet: validators.validateFactsheet,
};
const counts = { checked: 0, invalid: 0, byTopic: {} };

const sniffer = mqtt.connect(broker, { clientId: `sniffer-${process.pid}` });
sniffer.on("message", (topic, payload) => {
  const levels = topic.split("/");
  const kind = levels[4];
  const validate = check[kind];
  if (!validate) return;
  let obj;
  try {
    obj = JSON.parse(payload.toString());
  } catch (e) {
    counts.invalid++;
    say({ event: "invalid", topic, reason: "not JSON" });
    return;
  }
  counts.checked++;
  counts.byTopic[kind] = (counts.byTopic[kind] || 0) + 1;
  if (!validate(obj)) {
    counts.invalid++;
    say({ event: "invalid", topic, reason: JSON.stringify(validate.errors), payload: obj });
  }
  if (kind === "state") {
    say({
      event: "state", serial: levels[3], orderId: obj.orderId, orderUpdateId: obj.orderUpdateId,
      lastNodeId: obj.lastNodeId, lastNodeSequenceId: obj.lastNodeSequenceId,
      nodeStates: obj.nodeStates.map((n) => n.nodeId), driving: obj.driving,
      x: obj.agvPosition && obj.agvPosition.x, y: obj.agvPosition && obj.agvPosition.y,
      errors: obj.errors.map((e) => e.errorType + ": " + (e.errorDescription || "")),
      actions: obj.actionStates.map((a) => `${a.actionType}:${a.actionStatus}`),
      headerId: obj.headerId,
    });
  }
  if (kind === "order" || kind === "instantActions") {
    say({ event: kind, serial: levels[3], message: obj });
  }
});

const agvs = {};
function makeAgv(serial) {
  return new AgvController(
    { manufacturer, serialNumber: serial },
    { interfaceName: iface, transport: { brokerUrl: broker, heartbeat: 2 }, vdaVersion: "2.0.0" },
    { agvAdapterType: VirtualAgvAdapter, publishStateInterval: stateEvery, publishVisualizationInterval: 1000 },
    { initialPosition: { mapId: "local", x: 0, y: 0, theta: 0, lastNodeId: "0" }, vehicleSpeed: speed},
  );
}

async function main() {
  await new Promise((ok) => sniffer.subscribe(`${iface}/#`, { qos: 1 }, ok));
  for (let i = 1; i <= count; i++) {
    const serial = `agv${i}`;
    agvs[serial] = makeAgv(serial);
    await agvs[serial].start();
  }
  say({ event: "ready", count });
}

readline.createInterface({ input: process.stdin }).on("line", async (line) => {
  const [cmd, serial] = line.trim().split(/\s+/);
  try {
    if (cmd === "offline" && agvs[serial]) {
      await agvs[serial].stop();
      say({ event: "offline", serial });
    } else if (cmd === "online" && agvs[serial]) {
      agvs[serial] = makeAgv(serial);
      await agvs[serial].start();
      say({ event: "online", serial });
    } else if (cmd === "raw") {
      // raw TOPIC JSON: a message from nobody's vehicle (a test's hostile input).
      const rest = line.trim().split(/\s+/).slice(2).join(" ");
      sniffer.publish(serial, rest, { qos: 1 }, () => say({ event: "sent", topic: serial }));
    } else if (cmd === "stats") {
      say({ event: "checked", ...counts });
    } else if (cmd === "exit") {
      process.exit(0);
    }
  } catch (e) {
    say({ event: "error", reason: String(e) });
  }
});

main().catch((e) => {
  say({ event: "error", reason: String(e && e.stack || e) });
  process.exit(1);
});
