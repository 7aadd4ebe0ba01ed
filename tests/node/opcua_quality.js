// node-opcua watches one value's quality:
//   node opcua_quality.js ENDPOINT NODE_ID   (for tests/frontends/opcua/test_opcua_node.py)
// Subscribes (mode None, anonymous) and prints "STATUS <name> <sourceTimestamp ms>"
// for every notification, one line each, as they come; the test reads them as they
// arrive and ends the process when it has seen what it waits for.
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, TimestampsToReturn,
  ClientSubscription, ClientMonitoredItem,
} = require("node-opcua-client");

const [endpoint, nodeId] = process.argv.slice(2);

async function main() {
  const client = OPCUAClient.create({
    endpointMustExist: false, securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    certificateFile: process.env.UA_CERT, privateKeyFile: process.env.UA_KEY,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 500 },
  });
  await client.connect(endpoint);
  const session = await client.createSession();
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 1000,
    requestedMaxKeepAliveCount: 20, maxNotificationsPerPublish: 100,
    publishingEnabled: true, priority: 1,
  });
  const item = ClientMonitoredItem.create(subscription,
    { nodeId, attributeId: AttributeIds.Value },
    { samplingInterval: 0, discardOldest: true, queueSize: 100 }, TimestampsToReturn.Both);
  item.on("changed", (dv) => {
    const source = dv.sourceTimestamp ? dv.sourceTimestamp.getTime() : 0;
    process.stdout.write(`STATUS ${dv.statusCode.name} ${source}\n`);
  });
  process.stdout.write("SUBSCRIBED\n");
  // runs until the test ends it
}

main().catch((e) => { console.error(e); process.exit(1); });
