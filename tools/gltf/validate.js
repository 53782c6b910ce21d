// Validate one .glb/.gltf with the Khronos glTF validator; print its JSON report on stdout.
const fs = require("fs");
const validator = require("gltf-validator");

const file = process.argv[2];
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), { uri: file, maxIssues: 1000 }).then(
  (report) => console.log(JSON.stringify(report)),
  (err) => { console.error(String(err)); process.exit(2); },
);
