// Load a .glb with three.js's GLTFLoader (as a browser viewer would) and print what it built.
import fs from "node:fs";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const data = fs.readFileSync(process.argv[2]);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
new GLTFLoader().parse(buffer, "", (gltf) => {
  let mesh = null;
  gltf.scene.traverse((o) => { if (o.isMesh) mesh = o; });
  const clip = gltf.animations[0];
  console.log(JSON.stringify({
    vertices: mesh.geometry.attributes.position.count,
    normals: mesh.geometry.attributes.normal ? Array.from(mesh.geometry.attributes.normal.array.slice(0, 30)) : null,
    targetNormals: (mesh.geometry.morphAttributes.normal || []).length,
    targets: Object.keys(mesh.morphTargetDictionary),
    tracks: clip.tracks.map((t) => ({ name: t.name, times: t.times.length, values: t.values.length })),
    duration: clip.duration,
  }));
}, (err) => { console.error(String(err)); process.exit(2); });
