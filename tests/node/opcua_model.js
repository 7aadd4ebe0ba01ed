// node-opcua's client reads what an integrator reads first, for tests/frontends/opcua/test_opcua_node.py:
//   node opcua_model.js ENDPOINT GATEWAY_ID SENSOR USER PASSWORD
// The environment gives the client's certificate and key (UA_CERT, UA_KEY, PEM); the
// session is Basic256Sha256 SignAndEncrypt with the user.  Prints one JSON object:
// BuildInfo, the sensor's type (its browse name and node id, and the type's
// declarations with their modelling rules), the NodeIds of a value's EURange and
// EngineeringUnits found by browse path, and the StatusCodes of calls of the wrong shape.
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, UserTokenType,
  BrowseDirection, makeBrowsePath,
} = require("node-opcua-client");

const [endpoint, gateway, sensor, user, password] = process.argv.slice(2);

async function references(session, nodeId, referenceTypeId, direction) {
  const result = await session.browse({
    nodeId, referenceTypeId, browseDirection: direction || BrowseDirection.Forward,
    includeSubtypes: true, resultMask: 63,
  });
  return result.references;
}

async function declarations(session, typeId) {
  const out = {};
  for (const ref of await references(session, typeId, "HierarchicalReferences")) {
    const rules = await references(session, ref.nodeId, "HasModellingRule");
    out[ref.browseName.name] = rules.length ? rules[0].browseName.name : null;
  }
  return out;
}

async function main() {
  const client = OPCUAClient.create({
    endpointMustExist: false,
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile: process.env.UA_CERT,
    privateKeyFile: process.env.UA_KEY,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 500 },
  });
  await client.connect(endpoint);
  const session = await client.createSession(
    { type: UserTokenType.UserName, userName: user, password });
  const out = {};
  const build = await session.read({ nodeId: "ns=0;i=2260", attributeId: AttributeIds.Value });
  const info = build.value.value;
  out.build = { productName: info.productName, productUri: info.productUri,
    manufacturerName: info.manufacturerName, softwareVersion: info.softwareVersion,
    buildNumber: info.buildNumber, buildDate: info.buildDate.toISOString() };
  const ns = (await session.readNamespaceArray()).indexOf("urn:imu-gateway");
  const id = (path) => `ns=${ns};s=${gateway}.${path}`;
  const [typeRef] = await references(session, id(`Sensors.${sensor}`), "HasTypeDefinition");
  const [superRef] = await references(session, typeRef.nodeId, "HasSubtype",
    BrowseDirection.Inverse);
  out.type = { name: typeRef.browseName.name, nodeId: typeRef.nodeId.toString(),
    supertype: superRef.browseName.name,
    declarations: await declarations(session, typeRef.nodeId) };
  out.properties = {};
  for (const prop of ["EURange", "EngineeringUnits"]) {
    const found = await session.translateBrowsePath(
      makeBrowsePath(id(`Sensors.${sensor}.Angles.pitch`), `/0:${prop}`));
    out.properties[prop] = found.targets.map((t) => t.targetId.toString());
  }
  out.ns = ns;
  const call = async (method, inputArguments) => {
    const result = await session.call({ objectId: id(`Sensors.${sensor}`),
      methodId: id(`Sensors.${sensor}.${method}`), inputArguments });
    return { status: result.statusCode.name,
      inputs: (result.inputArgumentResults || []).map((s) => s.name) };
  };
  out.calls = {
    tooMany: await call("read_settings", [{ dataType: DataType.Int32, value: 1 }]),
    missing: await call("set_declination", []),
    wrongType: await call("set_declination", [{ dataType: DataType.String, value: "east" }]),
  };
  await session.close();
  await client.disconnect();
  console.log("RESULT " + JSON.stringify(out));
}

main().catch((e) => { console.error(e); process.exit(1); });
