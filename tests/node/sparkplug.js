// Eclipse Tahu's Sparkplug B payload codec (npm sparkplug-payload), for the tests: an
// independent reading of what the gateway publishes.  Reads one JSON request per line
// on stdin and writes one JSON answer per line:
//   {"decode": "<base64 payload>"}  -> the payload as Tahu decodes it
//   {"encode": {...payload...}}      -> {"b64": "<the encoded payload>"}
// 64-bit numbers (timestamps, seq, aliases, bdSeq) are written as plain numbers.
const sparkplug = require("sparkplug-payload").get("spBv1.0");
const readline = require("readline");

function plain(key, value) {
  if (value && typeof value === "object" && "low" in value && "high" in value &&
      "unsigned" in value) {
    return value.high * 4294967296 + (value.low >>> 0);
  }
  return value;
}

const lines = readline.createInterface({ input: process.stdin });
lines.on("line", (line) => {
  const request = JSON.parse(line);
  let answer;
  try {
    if ("decode" in request) {
      answer = sparkplug.decodePayload(Buffer.from(request.decode, "base64"));
    } else {
      answer = { b64: Buffer.from(sparkplug.encodePayload(request.encode)).toString("base64") };
    }
  } catch (e) {
    answer = { error: String(e) };
  }
  process.stdout.write(JSON.stringify(answer, plain) + "\n");
});
