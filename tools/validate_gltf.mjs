// Validate a glTF 2.0 asset (.glb or .gltf) with the Khronos glTF-Validator.
//
// Usage: node tools/validate_gltf.mjs <path> [--json]
//   Prints a one-line summary and one line per reported issue; with --json, prints the
//   full validation report (JSON) on stdout instead.
// Exit codes: 0 no errors, 1 the asset has errors, 2 usage or I/O problem.
// Install the validator first: npm ci --prefix tools
import fs from "node:fs";
import path from "node:path";
import validator from "gltf-validator";

const args = process.argv.slice(2);
const asJson = args.includes("--json");
const files = args.filter((a) => a !== "--json");
if (files.length !== 1) {
  console.error("usage: node tools/validate_gltf.mjs <file.glb|file.gltf> [--json]");
  process.exit(2);
}
const fullpath = path.resolve(files[0]);

function loadExternal(uri) {
  const file = path.resolve(path.dirname(fullpath), decodeURIComponent(uri));
  return fs.promises.readFile(file).then((data) => new Uint8Array(data));
}

let bytes;
try {
  bytes = new Uint8Array(fs.readFileSync(fullpath));
} catch (err) {
  console.error(`cannot read ${fullpath}: ${err.message}`);
  process.exit(2);
}

try {
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(fullpath),
    maxIssues: 1000,
    externalResourceFunction: loadExternal,
  });
  const issues = report.issues;
  if (asJson) {
    console.log(JSON.stringify(report, null, 2));
  } else {
    console.log(
      `${fullpath}: ${issues.numErrors} errors, ${issues.numWarnings} warnings, ` +
        `${issues.numInfos} infos, ${issues.numHints} hints (validator ${report.validatorVersion})`
    );
    const severity = ["error", "warning", "info", "hint"];
    for (const m of issues.messages) {
      console.log(`  ${severity[m.severity] ?? m.severity} ${m.code} at ${m.pointer ?? "-"}: ${m.message}`);
    }
  }
  // exitCode, not exit(): exit() would cut a long report still being written to a pipe (at 64 KiB)
  process.exitCode = issues.numErrors > 0 ? 1 : 0;
} catch (err) {
  console.error(`validator could not read ${fullpath}: ${err}`);
  process.exit(2);
}
