// node-opcua's client against the gateway's OPC UA server, for tests/frontends/opcua/test_opcua_node.py:
// an independent client that knows the server only from docs/opcua.md.
//   node opcua.js ENDPOINT GATEWAY_ID SENSOR [USER PASSWORD]
// The environment gives the client's certificate and key (UA_CERT, UA_KEY, PEM) and
// the security mode (UA_MODE: None or SignAndEncrypt, Basic256Sha256).
// Prints one JSON object: the browsed tree, the values read, the subscription's
// notifications of the sensor's Sequence, its pitch's history (raw over the last
// minute; Minimum and Maximum over the last 3 whole seconds, 1 s intervals), and a
// method call's result (with a user);
// or {"refused": why} when the session is refused.
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, TimestampsToReturn,
  ClientSubscription, ClientMonitoredItem, DataType, UserTokenType, AggregateFunction,
} = require("node-opcua-client");

const [endpoint, gateway, sensor, user, password] = process.argv.slice(2);

async function browseNames(session, nodeId) {
  const result = await session.browse(nodeId);
  return result.references.map((r) => ({ name: r.browseName.name, nodeId: r.nodeId.toString() }));
}

function values(result) {
  return { status: result.statusCode.value,
    values: ((result.historyData && result.historyData.dataValues) || []).map((dv) => ({ value: dv.value.value,
      source: dv.sourceTimestamp.getTime(), status: dv.statusCode.value })) };
}

async function history(session, nodeId) {
  const now = Date.now();
  const raw = await session.readHistoryValue(nodeId, new Date(now - 60000), new Date(now));
  const end = Math.floor(now / 1000) * 1000;
  const out = { raw: values(raw), start: end - 3000 };
  for (const [name, fn] of [["minimum", AggregateFunction.Minimum],
    ["maximum", AggregateFunction.Maximum]]) {
    out[name] = values(await session.readAggregateValue(
      { nodeId }, new Date(end - 3000), new Date(end), fn, 1000));
  }
  return out;
}

async function main() {
  const secure = process.env.UA_MODE === "SignAndEncrypt";
  const client = OPCUAClient.create({
    endpointMustExist: false,
    securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    certificateFile: process.env.UA_CERT,
    privateKeyFile: process.env.UA_KEY,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 500 },
  });
  const out = {};
  try {
    await client.connect(endpoint);
  } catch (e) {
    out.refused = String(e.message || e);
    console.log("RESULT " + JSON.stringify(out));
    return;
  }
  const identity = user
    ? { type: UserTokenType.UserName, userName: user, password }
    : { type: UserTokenType.Anonymous };
  let session;
  try {
    session = await client.createSession(identity);
  } catch (e) {
    out.refused = String(e.message || e);
    await client.disconnect();
    console.log("RESULT " + JSON.stringify(out));
    return;
  }
  const ns = (await session.readNamespaceArray()).indexOf("urn:imu-gateway");
  const id = (path) => `ns=${ns};s=${gateway}.${path}`;
  const objects = await browseNames(session, "ObjectsFolder");
  const top = objects.find((r) => r.name === "IMU Gateway");
  const gw = (await browseNames(session, top.nodeId)).find((r) => r.name === gateway);
  const folders = await browseNames(session, gw.nodeId);
  const sensors = await browseNames(session, folders.find((r) => r.name === "Sensors").nodeId);
  out.sensors = sensors.map((r) => r.name);
  const one = sensors.find((r) => r.name === sensor);
  out.children = (await browseNames(session, one.nodeId)).map((r) => r.name);
  out.values = {};
  for (const folder of ["Angles", "Acceleration", "AngularRate", "MagneticField", "Quaternion"]) {
    if (!out.children.includes(folder)) continue;
    for (const field of await browseNames(session, id(`Sensors.${sensor}.${folder}`))) {
      const dv = await session.read({ nodeId: field.nodeId, attributeId: AttributeIds.Value });
      out.values[field.name] = { value: dv.value.value, status: dv.statusCode.name };
    }
  }
  out.history = await history(session, id(`Sensors.${sensor}.Angles.pitch`));
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 100,
    requestedMaxKeepAliveCount: 10, maxNotificationsPerPublish: 100,
    publishingEnabled: true, priority: 1,
  });
  const item = ClientMonitoredItem.create(subscription,
    { nodeId: id(`Sensors.${sensor}.Sequence`), attributeId: AttributeIds.Value },
    { samplingInterval: 0, discardOldest: true, queueSize: 100 }, TimestampsToReturn.Both);
  out.notifications = [];
  await new Promise((resolve) => {
    item.on("changed", (dv) => {
      const v = dv.value.value;  // a UInt64 comes as [high, low]
      out.notifications.push({ value: Array.isArray(v) ? v[0] * 4294967296 + v[1] : Number(v),
        source: dv.sourceTimestamp.getTime(), status: dv.statusCode.name });
      if (out.notifications.length >= 5) resolve();
    });
  });
  await subscription.terminate();
  if (user) {
    const call = await session.call({
      objectId: id(`Sensors.${sensor}`), methodId: id(`Sensors.${sensor}.set_zero_type`),
      inputArguments: [{ dataType: DataType.String, value: "relative" }],
    });
    out.call = { status: call.statusCode.name,
      result: call.outputArguments.map((v) => v.value) };
  }
  await session.close();
  await client.disconnect();
  console.log("RESULT " + JSON.stringify(out));
}

main().catch((e) => { console.error(e); process.exit(1); });
