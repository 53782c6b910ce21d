// Load a .vrm with three.js's GLTFLoader + @pixiv/three-vrm (the VRM runtime three.js apps use) and, for every
// expression, set it alone to 1 and print which morph targets of which meshes it moves (JSON on stdout):
// {version, expressions: {name: {mesh: {target: influence}}}}. With a time (seconds) after the file, also
// play the file's first animation there and print the face meshes' influences before and after vrm.update.
import fs from "node:fs";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { VRMLoaderPlugin } from "@pixiv/three-vrm";

const data = fs.readFileSync(process.argv[2]);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
const loader = new GLTFLoader();
loader.register((parser) => new VRMLoaderPlugin(parser));
loader.parse(buffer, "", (gltf) => {
  const vrm = gltf.userData.vrm;
  if (!vrm) { console.error("not a VRM"); process.exit(2); }
  const meshes = [];
  vrm.scene.traverse((o) => { if (o.isMesh && o.morphTargetDictionary) meshes.push(o); });
  const manager = vrm.expressionManager;
  const out = {};
  for (const name of Object.keys(manager.expressionMap)) {
    for (const other of Object.keys(manager.expressionMap)) manager.setValue(other, 0);
    manager.setValue(name, 1);
    manager.update();
    const moved = {};
    for (const m of meshes) {
      const names = Object.keys(m.morphTargetDictionary);
      const hit = {};
      names.forEach((t) => { const v = m.morphTargetInfluences[m.morphTargetDictionary[t]]; if (v > 1e-6) hit[t] = v; });
      if (Object.keys(hit).length) moved[m.name] = hit;
    }
    out[name] = moved;
  }
  let played = null;
  if (process.argv[3] !== undefined) {
    for (const other of Object.keys(manager.expressionMap)) manager.setValue(other, 0);
    const mixer = new THREE.AnimationMixer(gltf.scene);
    mixer.clipAction(gltf.animations[0]).play();
    mixer.setTime(Number(process.argv[3]));
    const influences = () => Object.fromEntries(meshes.map((m) => [m.name, Array.from(m.morphTargetInfluences)]));
    const before = influences();
    vrm.update(0);
    played = { before, after: influences() };
  }
  console.log(JSON.stringify({ version: vrm.meta.metaVersion, expressions: out, played }));
}, (err) => { console.error(String(err)); process.exit(2); });
