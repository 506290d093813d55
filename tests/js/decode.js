// Reads msctl's ros2msg schemas (and CDR messages) the way Foxglove does: its ros2msg parser
// (@foxglove/rosmsg, `ros2: true`) and its CDR reader (@foxglove/rosmsg2-serialization).
// stdin: a JSON list of {name, definition, cdr?: base64}; stdout: one JSON list of
// {name, ok, error?, message?} in the same order. Used by tests/test_bag_foxglove.py.
"use strict";
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");

function plain(value) {
  if (typeof value === "bigint") return value.toString();
  if (ArrayBuffer.isView(value)) return Array.from(value, plain);
  if (Array.isArray(value)) return value.map(plain);
  if (value && typeof value === "object") {
    return Object.fromEntries(Object.entries(value).map(([k, v]) => [k, plain(v)]));
  }
  return value;
}

let input = "";
process.stdin.on("data", (chunk) => (input += chunk));
process.stdin.on("end", () => {
  const out = JSON.parse(input).map((item) => {
    try {
      const definitions = parse(item.definition, { ros2: true });
      const reader = new MessageReader(definitions);
      const result = { name: item.name, ok: true };
      if (item.cdr) {
        result.message = plain(reader.readMessage(Buffer.from(item.cdr, "base64")));
      }
      return result;
    } catch (err) {
      return { name: item.name, ok: false, error: String(err && err.message ? err.message : err) };
    }
  });
  process.stdout.write(JSON.stringify(out));
});
