// The Khronos glTF validator on files: prints a JSON list of their reports (issues, info).
// Usage: node validate.mjs FILE.glb [FILE.glb ...]
import fs from "node:fs";
import validator from "gltf-validator";

const reports = [];
for (const path of process.argv.slice(2)) {
  reports.push(await validator.validateBytes(new Uint8Array(fs.readFileSync(path)), { uri: path, maxIssues: 200 }));
}
process.stdout.write(JSON.stringify(reports));
