// An independent OPC UA server (node-opcua) for thermocomp's adapter tests.
// Exposes ns=1;s=Spindle1.ActSpeed (Double, rpm) and ns=1;s=Spindle1.ThermalOffset (Double,
// writable) plus ns=1;s=Spindle1.LockedOffset (read-only: writes are refused).
// Stdin lines "speed <rpm>" set the speed, "reset <token>" sets speed and offset to 0 and
// prints "reset <token>"; it prints "offset <value>" on every accepted write
// and "ready <port>" once listening (protocol lines start with "@@ "). Usage: node server.mjs PORT
import { OPCUAServer } from "node-opcua-server";
import { Variant, DataType } from "node-opcua-variant";
import { StatusCodes } from "node-opcua-status-code";
import readline from "node:readline";

const port = Number(process.argv[2] ?? 4841);
const server = new OPCUAServer({ port, resourcePath: "/thermocomp/node", allowAnonymous: true });
await server.initialize();
const ns = server.engine.addressSpace.getOwnNamespace();
const spindle = ns.addObject({ organizedBy: server.engine.addressSpace.rootFolder.objects, browseName: "Spindle1", nodeId: "s=Spindle1" });
let speed = 0.0;
let offset = 0.0;
ns.addVariable({
  componentOf: spindle, browseName: "ActSpeed", nodeId: "s=Spindle1.ActSpeed", dataType: "Double", minimumSamplingInterval: 100,
  value: { get: () => new Variant({ dataType: DataType.Double, value: speed }) },
});
ns.addVariable({
  componentOf: spindle, browseName: "ThermalOffset", nodeId: "s=Spindle1.ThermalOffset", dataType: "Double",
  accessLevel: "CurrentRead | CurrentWrite", userAccessLevel: "CurrentRead | CurrentWrite", minimumSamplingInterval: 100,
  value: {
    get: () => new Variant({ dataType: DataType.Double, value: offset }),
    set: (v) => {
      if (!Number.isFinite(v.value) || Math.abs(v.value) > 1000) return StatusCodes.BadOutOfRange;
      offset = v.value;
      console.log(`@@ offset ${offset}`);
      return StatusCodes.Good;
    },
  },
});
ns.addVariable({
  componentOf: spindle, browseName: "LockedOffset", nodeId: "s=Spindle1.LockedOffset", dataType: "Double",
  accessLevel: "CurrentRead", userAccessLevel: "CurrentRead", minimumSamplingInterval: 100,
  value: { get: () => new Variant({ dataType: DataType.Double, value: 0.0 }) },
});
await server.start();
console.log(`@@ ready ${port}`);
readline.createInterface({ input: process.stdin }).on("line", (line) => {
  const [cmd, arg] = line.trim().split(/\s+/);
  if (cmd === "speed") speed = Number(arg);
  if (cmd === "reset") {  // a server shared by tests: back to the start, then say so
    speed = 0.0;
    offset = 0.0;
    console.log(`@@ reset ${arg}`);
  }
  if (cmd === "quit") server.shutdown(100).then(() => process.exit(0));
});
process.stdin.on("end", () => server.shutdown(100).then(() => process.exit(0)));
