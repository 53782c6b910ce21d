// Write a face rig as .glb with three.js's GLTFExporter (npm three), as a web app would: input JSON
// {name, positions, indices, names, deltas: [[...] per shape], translation: [x, y, z]} (metres, flat arrays).
// Node has Blob but no FileReader, which the exporter's binary path reads its Blob with: a minimal one here.
import fs from "node:fs";
import * as THREE from "three";
import { GLTFExporter } from "three/examples/jsm/exporters/GLTFExporter.js";

globalThis.FileReader = class {
  readAsArrayBuffer(blob) { blob.arrayBuffer().then((b) => { this.result = b; this.onloadend(); }); }
};

const [input, output] = process.argv.slice(2);
const rig = JSON.parse(fs.readFileSync(input, "utf8"));
const geometry = new THREE.BufferGeometry();
geometry.setAttribute("position", new THREE.Float32BufferAttribute(rig.positions, 3));
geometry.setIndex(rig.indices);
geometry.morphTargetsRelative = true;
geometry.morphAttributes.position = rig.deltas.map((d, i) => {
  const a = new THREE.Float32BufferAttribute(d, 3);
  a.name = rig.names[i];
  return a;
});
const mesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial());
mesh.name = rig.name;
mesh.updateMorphTargets();
const head = new THREE.Group();
head.name = "Head";
head.position.fromArray(rig.translation);
head.add(mesh);
const scene = new THREE.Scene();
scene.add(head);
new GLTFExporter().parse(scene, (glb) => fs.writeFileSync(output, Buffer.from(glb)),
  (err) => { console.error(String(err)); process.exit(2); }, { binary: true });
