// Play a .glb's first animation with three.js's AnimationMixer (as a browser viewer does) and print
// the mesh's morph target influences at the given times: node three_sample.mjs FILE t0 t1 ...
import fs from "node:fs";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const data = fs.readFileSync(process.argv[2]);
const times = process.argv.slice(3).map(Number);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
new GLTFLoader().parse(buffer, "", (gltf) => {
  let mesh = null;
  gltf.scene.traverse((o) => { if (o.isMesh) mesh = o; });
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const action = mixer.clipAction(gltf.animations[0]);
  action.setLoop(THREE.LoopOnce);
  action.clampWhenFinished = true;
  action.play();
  const out = times.map((t) => { mixer.setTime(t); return Array.from(mesh.morphTargetInfluences); });
  console.log(JSON.stringify({ targets: Object.keys(mesh.morphTargetDictionary), influences: out }));
}, (err) => { console.error(String(err)); process.exit(2); });
