// Two clients of Foxglove's own protocol library (@foxglove/ws-protocol, over `ws`) against a
// running hammer_ros Foxglove server; prints what they saw as JSON. Usage: node ws_clients.mjs PORT
//  - the library's default subprotocol (foxglove.websocket.v1) alone: the HTTP status of the handshake;
//  - a watcher subscribed to every channel, counting the messages it gets twice (same channel, same log time)
//    while a cycler subscribes to every channel, waits for a model and unsubscribes, 30 times;
//  - the cycler then gets parameters, sets one (accepted) and another (refused), and calls ~/solve.
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const url = `ws://127.0.0.1:${process.argv[2]}`;
const SUBPROTOCOL = "foxglove.sdk.v1";
const CYCLES = 30;
const withTimeout = (promise, seconds, what) =>
  Promise.race([promise, new Promise((_, reject) => setTimeout(() => reject(new Error(`timeout: ${what}`)), seconds * 1000))]);

const legacyStatus = await new Promise((resolve) => {
  const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
  ws.on("unexpected-response", (_request, response) => resolve(response.statusCode));
  ws.on("open", () => { ws.close(); resolve(101); });
  ws.on("error", (error) => resolve(String(error)));
});

function connect() {
  const client = new FoxgloveClient({ ws: new WebSocket(url, [SUBPROTOCOL]) });
  const state = { client, channels: new Map(), info: null, services: [], statuses: [], parameters: {}, listeners: [] };
  client.on("serverInfo", (info) => { state.info = info; });
  client.on("advertise", (channels) => channels.forEach((c) => state.channels.set(c.id, c)));
  client.on("advertiseServices", (services) => state.services.push(...services));
  client.on("status", (status) => state.statuses.push(status.message));
  client.on("parameterValues", (event) => { state.parameters[event.id] = Object.fromEntries(event.parameters.map((p) => [p.name, p.value])); });
  client.on("message", (event) => state.listeners.forEach((listener) => listener(event)));
  return state;
}
const until = async (condition, seconds, what) => {
  const deadline = Date.now() + seconds * 1000;
  while (!condition()) {
    if (Date.now() > deadline) throw new Error(`timeout: ${what}`);
    await new Promise((resolve) => setTimeout(resolve, 20));
  }
};

const watcher = connect();
await until(() => watcher.channels.size > 0, 20, "the watcher's channels");
const seen = new Map(); // topic -> Set of log times
const twice = {};
const topicOf = new Map();
for (const channel of watcher.channels.values()) {
  topicOf.set(watcher.client.subscribe(channel.id), channel.topic);
  seen.set(channel.topic, new Set());
  twice[channel.topic] = 0;
}
watcher.listeners.push((event) => {
  const topic = topicOf.get(event.subscriptionId);
  const stamps = seen.get(topic);
  if (stamps.has(event.timestamp)) twice[topic] += 1;
  stamps.add(event.timestamp);
});
const modelTopic = [...watcher.channels.values()].find((c) => c.topic.endsWith("/dashboard/model")).topic;
await until(() => seen.get(modelTopic).size > 0, 20, "the watcher's first model");

const cycler = connect();
await until(() => cycler.channels.size > 0 && cycler.services.length > 0, 20, "the cycler's channels and services");
let cyclesWithModel = 0;
for (let k = 0; k < CYCLES; k += 1) {
  const ids = new Map([...cycler.channels.values()].map((c) => [cycler.client.subscribe(c.id), c.topic]));
  try {
    await withTimeout(new Promise((resolve) => {
      cycler.listeners = [(event) => { if (ids.get(event.subscriptionId) === modelTopic) resolve(); }];
    }), 2, "a model");
    cyclesWithModel += 1;
  } catch { /* counted as a cycle without a model */ }
  ids.forEach((_, id) => cycler.client.unsubscribe(id));
}
cycler.client.getParameters(["window", "solve_rate", "method"], "get");
cycler.client.setParameters([{ name: "solve_rate", value: 3.0, type: "float64" }], "accepted");
cycler.client.setParameters([{ name: "window", value: 100 }], "refused");
await until(() => cycler.parameters.get && cycler.parameters.accepted && cycler.parameters.refused && cycler.statuses.length, 20, "parameter values");
const solve = cycler.services.find((s) => s.name.endsWith("/solve"));
const response = await withTimeout(new Promise((resolve) => {
  cycler.client.on("serviceCallResponse", (event) => resolve(event));
  cycler.client.sendServiceCallRequest({ serviceId: solve.id, callId: 1, encoding: "json", data: new TextEncoder().encode("{}") });
}), 30, "the ~/solve response");
console.log(JSON.stringify({
  legacy_status: legacyStatus,
  capabilities: cycler.info.capabilities,
  services: cycler.services.map((s) => s.name).sort(),
  watcher_messages: Object.fromEntries([...seen].map(([topic, stamps]) => [topic, stamps.size])),
  watcher_duplicates: twice,
  cycles_with_model: cyclesWithModel,
  parameters: cycler.parameters,
  statuses: cycler.statuses,
  solve: { callId: response.callId, encoding: response.encoding, payload: JSON.parse(new TextDecoder().decode(response.data)) },
}));
watcher.client.close();
cycler.client.close();
process.exit(0);
