// A VDA 5050 master control from vda-5050-lib (MasterController) driving one vehicle,
// and the sniffer checking every message on the interface.
//
//   node master.js --broker mqtt://127.0.0.1:PORT [--interface uagv]
//        --manufacturer muster --serial D1
//
// Standard input, one command a line:
//   order JSON     assignOrder() with this headerless order; prints {"event":
//                  "orderProcessed", withError, byCancelation, active} and
//                  {"event": "nodeTraversed", nodeId} as they come
//   instant TYPE   initiateInstantActions() with one action of TYPE; prints
//                  {"event": "instantActionState", actionType, actionStatus}
//   raw TOPIC TEXT publishes TEXT as is (prints {"event": "sent"})
//   stats          {"event": "checked", ...counts of checked messages}
//   exit
// The vehicle's connection states come as {"event": "connection", ...} (sniffer).
"use strict";
const { MasterController } = require("vda-5050-lib");
const { startSniffer, parseArgs } = require("./sniffer");
const readline = require("readline");

const args = parseArgs();
const broker = args.broker;
const iface = args.interface || "uagv";
const agvId = { manufacturer: args.manufacturer || "muster", serialNumber: args.serial || "D1" };
const say = (o) => process.stdout.write(JSON.stringify(o) + "\n");
const sniffer = startSniffer(broker, iface, say);
const mc = new MasterController(
  { interfaceName: iface, transport: { brokerUrl: broker, heartbeat: 2 }, vdaVersion: "2.0.0" },
  { targetAgvs: agvId },
);

let n = 0;
readline.createInterface({ input: process.stdin }).on("line", async (line) => {
  const space = line.indexOf(" ");
  const cmd = space < 0 ? line.trim() : line.slice(0, space);
  const rest = space < 0 ? "" : line.slice(space + 1);
  try {
    if (cmd === "order") {
      const order = JSON.parse(rest);
      const sent = await mc.assignOrder(agvId, order, {
        onOrderProcessed: (withError, byCancelation, active, ctx) => say({
          event: "orderProcessed", orderId: ctx.order.orderId, withError: withError ? String(withError.errorType + ": " + withError.errorDescription) : null,
          byCancelation, active, lastNodeId: ctx.state.lastNodeId,
          x: ctx.state.agvPosition && ctx.state.agvPosition.x, y: ctx.state.agvPosition && ctx.state.agvPosition.y,
        }),
        onNodeTraversed: (node) => say({ event: "nodeTraversed", nodeId: node.nodeId, sequenceId: node.sequenceId }),
      });
      say({ event: "orderSent", orderId: sent.orderId, headerId: sent.headerId, at: Date.now() });
    } else if (cmd === "instant") {
      n++;
      await mc.initiateInstantActions(agvId, {
        instantActions: [{ actionId: `test-${process.pid}-${n}`, actionType: rest.trim(), blockingType: "NONE" }],
      }, {
        onActionStateChanged: (as, withError) => say({
          event: "instantActionState", actionType: as.actionType, actionStatus: as.actionStatus,
          withError: withError ? String(withError.errorDescription) : null,
        }),
        onActionError: (err) => say({ event: "instantActionError", error: String(err.errorDescription) }),
      });
    } else if (cmd === "raw") {
      // raw TOPIC TEXT: published as is (a test's hostile input).
      const sp = rest.indexOf(" ");
      const topic = rest.slice(0, sp);
      sniffer.client.publish(topic, rest.slice(sp + 1), { qos: 1 }, () => say({ event: "sent", topic }));
    } else if (cmd === "stats") {
      say({ event: "checked", ...sniffer.counts });
    } else if (cmd === "exit") {
      process.exit(0);
    }
  } catch (e) {
    say({ event: "error", reason: String(e && e.stack || e) });
  }
});

(async () => {
  await sniffer.ready;
  await mc.start();
  say({ event: "ready" });
})().catch((e) => {
  say({ event: "error", reason: String(e && e.stack || e) });
  process.exit(1);
});
