#!/usr/bin/env node
// Print the Khronos glTF-Validator's report of a glTF or GLB file as JSON on stdout.
//
//   node tests/io/validate_gltf.cjs FILE
//
// The validator module (npm gltf-validator) is found by Node's own lookup: a node_modules folder
// in this file's folder or one above it (.ci/run installs it at the repository root), or NODE_PATH.
// Exit status: 0 with the report printed; 3 when the gltf-validator module is not installed (checked
// first, so running it without FILE tells whether it is); 2 for a missing FILE or one the validator
// cannot read.
"use strict";
const fs = require("fs");
const path = require("path");

function main(argv) {
  let validator;
  try {
    validator = require("gltf-validator");
  } catch (err) {
    process.stderr.write("gltf-validator is not installed (the npm install line of .ci/run)\n");
    return Promise.resolve(3);
  }
  if (argv.length !== 1) {
    process.stderr.write("usage: validate_gltf.cjs FILE\n");
    return Promise.resolve(2);
  }
  const file = argv[0];
  let bytes;
  try {
    bytes = new Uint8Array(fs.readFileSync(file));
  } catch (err) {
    process.stderr.write(`${file}: ${err.message}\n`);
    return Promise.resolve(2);
  }
  const readExternal = (uri) =>
    fs.promises.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)));
  return validator
    .validateBytes(bytes, { uri: path.basename(file), maxIssues: 0, externalResourceFunction: readExternal })
    .then(
      (report) => {
        process.stdout.write(JSON.stringify(report, null, 2) + "\n");
        return 0;
      },
      (err) => {
        process.stderr.write(`${file}: the validator could not read it: ${err}\n`);
        return 2;
      },
    );
}

main(process.argv.slice(2)).then((code) => {
  process.exitCode = code;
});
