// The Khronos glTF validator on one file: prints its JSON report (issues, info) to stdout.
// Usage: node validate.mjs FILE.glb
import fs from "node:fs";
import validator from "gltf-validator";

const path = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(path)), {
  uri: path,
  maxIssues: 200,
});
process.stdout.write(JSON.stringify(report));
