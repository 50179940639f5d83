// Reads MCAP files with Foxglove's own readers (@mcap/core; ROS 2 messages with
// @foxglove/rosmsg + @foxglove/rosmsg2-serialization, JSON messages against their JSON schemas)
// and prints {"topic": {"messages": n, "encoding": "...", "errors": [...]}} per file as JSON.
// Usage: node check_mcap.mjs FILE.mcap ...   (exit code 1 when any message fails)
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import { decompress } from "fzstd";

function fileReadable(handle, size) {
  return {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const buffer = new Uint8Array(Number(length));
      await handle.read(buffer, 0, buffer.length, Number(offset));
      return buffer;
    },
  };
}

const TYPES = {
  object: (v) => v !== null && typeof v === "object" && !Array.isArray(v),
  array: Array.isArray,
  string: (v) => typeof v === "string",
  boolean: (v) => typeof v === "boolean",
  null: (v) => v === null,
  integer: Number.isInteger,
  number: (v) => typeof v === "number",
};

// Where a JSON value does not follow its JSON schema: undeclared keys and wrong types.
function mismatches(schema, value, path) {
  if (schema.type !== undefined) {
    const types = Array.isArray(schema.type) ? schema.type : [schema.type];
    if (!types.some((t) => TYPES[t](value))) return [`${path || "."}: not ${types.join("|")}`];
  }
  const found = [];
  if (TYPES.object(value)) {
    const properties = schema.properties ?? {};
    for (const [key, item] of Object.entries(value)) {
      if (key in properties) found.push(...mismatches(properties[key], item, `${path}.${key}`));
      else if (schema.additionalProperties !== undefined) found.push(...mismatches(schema.additionalProperties, item, `${path}.${key}`));
      else found.push(`${path}.${key}: not declared`);
    }
  } else if (Array.isArray(value) && schema.items !== undefined) {
    value.forEach((item, i) => found.push(...mismatches(schema.items, item, `${path}[${i}]`)));
  }
  return found;
}

const report = {};
let failed = false;
for (const path of process.argv.slice(2)) {
  const handle = await open(path, "r");
  const { size } = await handle.stat();
  const reader = await McapIndexedReader.Initialize({
    readable: fileReadable(handle, size),
    decompressHandlers: { zstd: (data, decompressedSize) => decompress(data, new Uint8Array(Number(decompressedSize))) },
  });
  const decoders = new Map();
  const topics = {};
  for (const [id, channel] of reader.channelsById) {
    const schema = reader.schemasById.get(channel.schemaId);
    const text = new TextDecoder().decode(schema.data);
    let decode;
    if (channel.messageEncoding === "cdr" && schema.encoding === "ros2msg") {
      const messageReader = new MessageReader(parse(text, { ros2: true }));
      decode = (data) => (messageReader.readMessage(data), []);
    } else if (channel.messageEncoding === "json" && schema.encoding === "jsonschema") {
      const jsonSchema = JSON.parse(text);
      decode = (data) => mismatches(jsonSchema, JSON.parse(new TextDecoder().decode(data)), "");
    } else {
      decode = () => [`no reader for ${channel.messageEncoding} / ${schema.encoding}`];
    }
    decoders.set(id, decode);
    topics[channel.topic] = { messages: 0, encoding: `${channel.messageEncoding}/${schema.encoding}`, errors: [] };
  }
  for await (const message of reader.readMessages()) {
    const channel = reader.channelsById.get(message.channelId);
    const entry = topics[channel.topic];
    entry.messages += 1;
    try {
      entry.errors.push(...decoders.get(message.channelId)(message.data));
    } catch (error) {
      entry.errors.push(String(error));
    }
    if (entry.errors.length) failed = true;
    entry.errors = entry.errors.slice(0, 5);
  }
  await handle.close();
  report[path] = topics;
}
console.log(JSON.stringify(report));
process.exit(failed ? 1 : 0);
