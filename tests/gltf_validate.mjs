// Validate GLB files with the Khronos glTF validator and print the reports as JSON.
//
//   node tests/gltf_validate.mjs PREFIX FILE.glb [FILE.glb ...]
//
// PREFIX is the `npm install --prefix` directory holding node_modules/gltf-validator
// (tests/test_gltf.py installs a pinned version there). Prints one JSON array with
// the validator's report for each file, in order; exits 2 on a usage or load error.
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import path from "node:path";

const [prefix, ...files] = process.argv.slice(2);
if (!prefix || files.length === 0) {
  console.error("usage: node gltf_validate.mjs PREFIX FILE.glb [FILE.glb ...]");
  process.exit(2);
}

const require = createRequire(import.meta.url);
const validator = require(path.resolve(prefix, "node_modules", "gltf-validator"));

const reports = [];
for (const file of files) {
  const bytes = new Uint8Array(await readFile(file));
  // maxIssues 0: every issue, so a test can show all of them
  reports.push(await validator.validateBytes(bytes, { uri: path.basename(file), maxIssues: 0 }));
}
process.stdout.write(JSON.stringify(reports));
