// node-opcua subscribes to a sensor's events and acknowledges its alarm:
//   node opcua_alarm.js ENDPOINT GATEWAY_ID SENSOR ALARM USER PASSWORD
// (for tests/frontends/opcua/test_opcua_alarms.py; the environment gives the client's
// certificate and key, UA_CERT and UA_KEY, PEM; Basic256Sha256 SignAndEncrypt).
// Knows the server only from docs/opcua.md: the sensor object is a notifier, the alarm
// a condition with the standard fields. Prints "SUBSCRIBED" once its event item is
// on; then, when the alarm's event comes active and unacknowledged, acknowledges it
// with that event's EventId (session.acknowledgeCondition: Part 9's Acknowledge on
// the ConditionId); when the acknowledged event comes, prints one line
// "RESULT {json}" with both events' fields and the Acknowledge's StatusCode, and ends.
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, TimestampsToReturn,
  ClientSubscription, ClientMonitoredItem, UserTokenType, constructEventFilter,
} = require("node-opcua-client");

const [endpoint, gateway, sensor, alarm, user, password] = process.argv.slice(2);
const FIELDS = ["EventId", "EventType", "SourceName", "SourceNode", "Time", "Message",
  "Severity", "ConditionName", "Retain", "ActiveState", "ActiveState.Id", "AckedState",
  "AckedState.Id", "HighLimit", "ClientUserId", "ConditionId"];

function plain(name, variant) {
  const value = variant.value;
  if (value === null || value === undefined) return null;
  if (Buffer.isBuffer(value)) return value.toString("hex");
  if (value instanceof Date) return value.getTime();
  if (value.text !== undefined) return value.text;
  if (typeof value === "object" && value.toString) return value.toString();
  return value;
}

async function main() {
  const client = OPCUAClient.create({
    endpointMustExist: false, securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile: process.env.UA_CERT, privateKeyFile: process.env.UA_KEY,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 500 },
  });
  await client.connect(endpoint);
  const session = await client.createSession(
    { type: UserTokenType.UserName, userName: user, password });
  const ns = (await session.readNamespaceArray()).indexOf("urn:imu-gateway");
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 1000,
    requestedMaxKeepAliveCount: 20, maxNotificationsPerPublish: 100,
    publishingEnabled: true, priority: 1,
  });
  const item = ClientMonitoredItem.create(subscription,
    { nodeId: `ns=${ns};s=${gateway}.Sensors.${sensor}`, attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, discardOldest: true, queueSize: 100,
      filter: constructEventFilter(FIELDS) }, TimestampsToReturn.Both);
  const out = { ns, events: [] };
  item.on("changed", async (fields) => {
    const event = {};
    FIELDS.forEach((name, i) => { event[name] = plain(name, fields[i]); });
    if (event.ConditionName !== alarm) return;
    out.events.push(event);
    if (event["ActiveState.Id"] && !event["AckedState.Id"] && out.ack === undefined) {
      out.ack = "pending";
      const status = await session.acknowledgeCondition(
        fields[FIELDS.indexOf("ConditionId")].value, fields[0].value, "seen from node-opcua");
      out.ack = status.name;
    } else if (event["ActiveState.Id"] && event["AckedState.Id"]) {
      console.log("RESULT " + JSON.stringify(out));
      await subscription.terminate();
      await session.close();
      await client.disconnect();
      process.exit(0);
    }
  });
  item.on("initialized", () => process.stdout.write("SUBSCRIBED\n"));
}

main().catch((e) => { console.error(e); process.exit(1); });
