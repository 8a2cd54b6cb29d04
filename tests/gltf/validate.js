// Validates a glTF asset with the Khronos glTF validator
// (https://github.com/KhronosGroup/glTF-Validator): prints its report as
// JSON; exit 0 when it finds no error, 1 otherwise, 2 when it cannot run.
// Usage: node validate.js ASSET.gltf
const fs = require('fs');
const path = require('path');
const validator = require('gltf-validator');

const file = process.argv[2];
if (!file) {
  console.error('usage: node validate.js ASSET.gltf');
  process.exit(2);
}
const dir = path.dirname(file);
validator
  .validateBytes(new Uint8Array(fs.readFileSync(file)), {
    uri: file,
    // Buffers and images beside the asset, by their relative URIs.
    externalResourceFunction: (uri) =>
      new Promise((resolve, reject) => {
        fs.readFile(path.join(dir, decodeURIComponent(uri)), (err, data) =>
          err ? reject(err.toString()) : resolve(new Uint8Array(data)),
        );
      }),
  })
  .then((report) => {
    console.log(JSON.stringify(report, null, 1));
    process.exit(report.issues.numErrors > 0 ? 1 : 0);
  })
  .catch((err) => {
    console.error(err);
    process.exit(2);
  });
