// A listener on a whole VDA 5050 interface that checks every message against
// vda-5050-lib's VDA 5050 2.0 validators (generated from the official JSON schemas),
// and reports states, orders and instant actions as JSON lines.
"use strict";
const validators = require("vda-5050-lib/common/vda-5050-validators-2.0");
const mqtt = require("mqtt");

const check = {
  connection: validators.validateConnection,
  state: validators.validateState,
  order: validators.validateOrder,
  instantActions: validators.validateInstantActions,
  visualization: validators.validateVisualization,
  factsheet: validators.validateFactsheet,
};

/// `--key value` pairs of the command line.
function parseArgs() {
  const args = {};
  for (let i = 2; i < process.argv.length; i += 2) {
    args[process.argv[i].replace(/^--/, "")] = process.argv[i + 1];
  }
  return args;
}

/// Subscribes to `${iface}/#`; `say` gets {event: "invalid" | "state" | "order" |
/// "instantActions" | "connection" | "factsheet", ...}.
function startSniffer(broker, iface, say) {
  const counts = { checked: 0, invalid: 0, byTopic: {} };
  const client = mqtt.connect(broker, { clientId: `sniffer-${process.pid}` });
  client.on("message", (topic, payload) => {
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
      return;
    }
    if (kind === "state") {
      say({
        event: "state", serial: levels[3], orderId: obj.orderId, orderUpdateId: obj.orderUpdateId,
        lastNodeId: obj.lastNodeId, lastNodeSequenceId: obj.lastNodeSequenceId,
        nodeStates: obj.nodeStates.map((n) => n.nodeId), driving: obj.driving,
        paused: obj.paused,
        x: obj.agvPosition && obj.agvPosition.x, y: obj.agvPosition && obj.agvPosition.y,
        errors: obj.errors.map((e) => e.errorType + ": " + (e.errorDescription || "")),
        actions: obj.actionStates.map((a) => `${a.actionType}:${a.actionStatus}`),
        headerId: obj.headerId,
      });
    } else if (kind !== "visualization") {
      say({ event: kind, serial: levels[3], message: obj });
    }
  });
  const ready = new Promise((ok) => client.on("connect", () => client.subscribe(`${iface}/#`, { qos: 1 }, ok)));
  return { client, counts, ready };
}

module.exports = { startSniffer, parseArgs };
