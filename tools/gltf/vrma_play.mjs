// Play a VRM Animation (.vrma) on a VRM with three-vrm and three-vrm-animation, as a three.js VRM app does:
// node vrma_play.mjs avatar.vrm take.vrma T... prints, at each time T (seconds), every morphed mesh's
// influences after vrm.update and the head bone's world rotation change from its rest (x, y, z, w).
import fs from "node:fs";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { VRMLoaderPlugin } from "@pixiv/three-vrm";
import { VRMAnimationLoaderPlugin, createVRMAnimationClip } from "@pixiv/three-vrm-animation";

const [vrmFile, vrmaFile, ...times] = process.argv.slice(2);
const loader = new GLTFLoader();
loader.register((parser) => new VRMLoaderPlugin(parser));
loader.register((parser) => new VRMAnimationLoaderPlugin(parser));
const load = (file) => new Promise((resolve, reject) => {
  const data = fs.readFileSync(file);
  loader.parse(data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength), "", resolve, reject);
});

try {
  const vrm = (await load(vrmFile)).userData.vrm;
  const animation = (await load(vrmaFile)).userData.vrmAnimations[0];
  const meshes = [];
  vrm.scene.traverse((o) => { if (o.isMesh && o.morphTargetDictionary) meshes.push(o); });
  const head = vrm.humanoid.getRawBoneNode("head");
  vrm.scene.updateMatrixWorld(true);
  const rest = head.getWorldQuaternion(new THREE.Quaternion());
  const mixer = new THREE.AnimationMixer(vrm.scene);
  const clip = createVRMAnimationClip(animation, vrm);
  mixer.clipAction(clip).play();
  const frames = times.map(Number).map((t) => {
    mixer.setTime(t);
    vrm.update(0);
    vrm.scene.updateMatrixWorld(true);
    const turn = head.getWorldQuaternion(new THREE.Quaternion()).multiply(rest.clone().invert());
    return { ...Object.fromEntries(meshes.map((m) => [m.name, Array.from(m.morphTargetInfluences)])),
      head: turn.toArray() };
  });
  console.log(JSON.stringify({ tracks: clip.tracks.map((t) => t.name), frames }));
} catch (err) {
  console.error(String(err));
  process.exit(2);
}
