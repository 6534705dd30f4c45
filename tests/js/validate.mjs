// Validate glTF files with the Khronos glTF validator; print one JSON report per file, one per line.
// Usage: node validate.mjs FILE.glb [FILE.glb ...]
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

for (const path of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(path)), { maxIssues: 100 });
  console.log(JSON.stringify({ path, issues: report.issues, info: report.info }));
}
