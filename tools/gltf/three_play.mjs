// Load a .glb/.vrm with three.js's GLTFLoader, play its first animation with an AnimationMixer at the given
// times (seconds) and print every morphed mesh's target names and influences there, and the local quaternion
// (x, y, z, w) of every node a rotation track turns (JSON on stdout).
import fs from "node:fs";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const [file, ...times] = process.argv.slice(2);
const data = fs.readFileSync(file);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
new GLTFLoader().parse(buffer, "", (gltf) => {
  const meshes = [];
  gltf.scene.traverse((o) => { if (o.isMesh && o.morphTargetDictionary) meshes.push(o); });
  const clip = gltf.animations[0];
  const mixer = new THREE.AnimationMixer(gltf.scene);
  mixer.clipAction(clip).play();
  const turned = clip.tracks.filter((t) => t.name.endsWith(".quaternion")).map((t) => t.name.split(".")[0]);
  const frames = times.map(Number).map((t) => {
    mixer.setTime(t);
    return {
      ...Object.fromEntries(meshes.map((m) => [m.name, Array.from(m.morphTargetInfluences)])),
      rotations: Object.fromEntries(turned.map((n) => [n, gltf.scene.getObjectByName(n).quaternion.toArray()])),
    };
  });
  console.log(JSON.stringify({
    clip: clip.name, duration: clip.duration, tracks: clip.tracks.map((t) => t.name),
    meshes: Object.fromEntries(meshes.map((m) => [m.name, {
      vertices: m.geometry.attributes.position.count,
      targets: Object.keys(m.morphTargetDictionary).sort((a, b) => m.morphTargetDictionary[a] - m.morphTargetDictionary[b]),
    }])),
    frames,
  }));
}, (err) => { console.error(String(err)); process.exit(2); });
