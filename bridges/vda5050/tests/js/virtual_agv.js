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
const { startSniffer, parseArgs } = require("./sniffer");
const readline = require("readline");

const args = parseArgs();
const broker = args.broker;
const iface = args.interface || "uagv";
const manufacturer = args.manufacturer || "acme";
const count = parseInt(args.count || "1", 10);
const speed = parseFloat(args.speed || "2");
const stateEvery = parseInt(args["state-every-ms"] || "30000", 10);
const say = (o) => process.stdout.write(JSON.stringify(o) + "\n");

const sniffer = startSniffer(broker, iface, say);

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
  await sniffer.ready;
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
      sniffer.client.publish(serial, rest, { qos: 1 }, () => say({ event: "sent", topic: serial }));
    } else if (cmd === "stats") {
      say({ event: "checked", ...sniffer.counts });
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
