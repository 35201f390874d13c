// An independent OPC UA client (node-opcua) for thermocomp's virtual CNC:
// connect, find Spindle1 by browse path, read ActSpeed and SimTime, write ThermalOffset,
// read it back, read AtSpeed and Cutting. Prints one JSON line. Usage: node vcnc_client.mjs URL OFFSET_UM
import { OPCUAClient, AttributeIds, DataType, makeBrowsePath, StatusCodes } from "node-opcua-client";

const [url, offsetArg] = process.argv.slice(2);
const offset = Number(offsetArg ?? "-12.5");
const client = OPCUAClient.create({ endpointMustExist: false, connectionStrategy: { maxRetry: 2 } });
const out = {};
try {
  await client.connect(url);
  const session = await client.createSession();
  const ns = (await session.readNamespaceArray()).indexOf("urn:thermocomp:virtual-cnc");
  out.namespace = ns;
  const path = makeBrowsePath("RootFolder",
    `/Objects/${ns}:CncInterface/${ns}:CncSpindleList/${ns}:Spindle1/${ns}:ActSpeed`);
  const res = await session.translateBrowsePath(path);
  out.browse_status = res.statusCode.name;
  const speedId = res.targets[0].targetId.toString();
  out.act_speed_node = speedId;
  const speed = await session.read({ nodeId: speedId, attributeId: AttributeIds.Value });
  out.act_speed_rpm = speed.value.value;
  const t1 = await session.read({ nodeId: `ns=${ns};s=/CncInterface/Simulation/SimTime`, attributeId: AttributeIds.Value });
  out.sim_time_s = t1.value.value;
  const offId = `ns=${ns};s=/CncInterface/CncSpindleList/Spindle1/ThermalOffset`;
  const st = await session.write({ nodeId: offId, attributeId: AttributeIds.Value,
    value: { value: { dataType: DataType.Double, value: offset } } });
  out.write_status = st.name;
  const back = await session.read({ nodeId: offId, attributeId: AttributeIds.Value });
  out.offset_readback_um = back.value.value;
  await new Promise((r) => setTimeout(r, 300));
  const [err, tru] = await session.read([
    { nodeId: `ns=${ns};s=/CncInterface/Simulation/ToolTipError`, attributeId: AttributeIds.Value },
    { nodeId: `ns=${ns};s=/CncInterface/Simulation/TrueElongation`, attributeId: AttributeIds.Value }]);
  out.tool_tip_error_um = err.value.value;
  out.true_elongation_um = tru.value.value;
  const [atSpeed, cutting] = await session.read([
    { nodeId: `ns=${ns};s=/CncInterface/CncSpindleList/Spindle1/AtSpeed`, attributeId: AttributeIds.Value },
    { nodeId: `ns=${ns};s=/CncInterface/CncSpindleList/Spindle1/Cutting`, attributeId: AttributeIds.Value }]);
  out.at_speed = atSpeed.value.value;
  out.cutting = cutting.value.value;
  out.cutting_type = DataType[cutting.value.dataType];
  await session.close();
  out.ok = out.write_status === StatusCodes.Good.name;
} catch (e) {
  out.ok = false;
  out.error = String(e && e.message ? e.message : e);
} finally {
  await client.disconnect();
}
console.log(JSON.stringify(out));
process.exit(out.ok ? 0 : 1);
