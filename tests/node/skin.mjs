// three.js as an independent reader and skinner of a rigged .glb (no browser, no GPU).
// Usage: node skin.mjs FILE.glb POSE.json OUT.bin
// POSE.json: {"bones": {name: {"translation": [x, y, z], "rotation": [x, y, z, w]}},
//             "morphs": [weight, ...] (optional), "time": seconds (optional)}: local transforms of
//             the named joint nodes; with "time", the file's first animation is played by an
//             AnimationMixer and sampled at that time first.
// Writes the skinned vertex positions as float64 (V * 3) computed by three.js
// (SkinnedMesh.getVertexPosition: morph targets, then bindMatrix, bones' matrixWorld and
// boneInverses, weighted, exactly what its skinning shader does), and prints a JSON summary.
import fs from "node:fs";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { AnimationMixer, LoopOnce, Vector3 } from "three";

const [file, posePath, outPath] = process.argv.slice(2);
const bytes = fs.readFileSync(file);
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const pose = JSON.parse(fs.readFileSync(posePath, "utf8"));

const gltf = await new Promise((resolve, reject) => new GLTFLoader().parse(buffer, "", resolve, reject));
const skinned = [];
gltf.scene.traverse((o) => { if (o.isSkinnedMesh) skinned.push(o); });
if (skinned.length !== 1) throw new Error(`expected one SkinnedMesh, found ${skinned.length}`);
const mesh = skinned[0];
// three.js strips "." from node names ("breast.L" -> "breastL", PropertyBinding.sanitizeNodeName)
// and keeps the file's name in userData.name: bones are looked up by that.
const bones = new Map(mesh.skeleton.bones.map((b) => [b.userData.name ?? b.name, b]));
let animation = null;
if (pose.time !== undefined) {
  if (gltf.animations.length === 0) throw new Error("the file holds no animation");
  const clip = gltf.animations[0];
  const mixer = new AnimationMixer(gltf.scene);
  // played once and held at its end: a looping action wraps its last frame back to the first
  const action = mixer.clipAction(clip);
  action.setLoop(LoopOnce);
  action.clampWhenFinished = true;
  action.play();
  mixer.setTime(pose.time);
  animation = { name: clip.name, duration: clip.duration, tracks: clip.tracks.length };
}
for (const [name, t] of Object.entries(pose.bones || {})) {
  const bone = bones.get(name);
  if (!bone) throw new Error(`no bone ${name}`);
  bone.position.fromArray(t.translation);
  bone.quaternion.fromArray(t.rotation);
}
if (pose.morphs) {
  pose.morphs.forEach((w, i) => { mesh.morphTargetInfluences[i] = w; });
}
gltf.scene.updateMatrixWorld(true);
const n = mesh.geometry.attributes.position.count;
const out = new Float64Array(3 * n);
const v = new Vector3();
for (let i = 0; i < n; i++) {
  mesh.getVertexPosition(i, v);
  v.applyMatrix4(mesh.matrixWorld);
  out[3 * i] = v.x; out[3 * i + 1] = v.y; out[3 * i + 2] = v.z;
}
fs.writeFileSync(outPath, Buffer.from(out.buffer));
process.stdout.write(JSON.stringify({
  vertices: n,
  bones: mesh.skeleton.bones.length,
  bone_names: mesh.skeleton.bones.map((b) => b.userData.name ?? b.name),
  bone_extras: mesh.skeleton.bones.map((b) => b.userData),
  morph_targets: mesh.morphTargetDictionary || {},
  material: mesh.material.name,
  has_normals: "normal" in mesh.geometry.attributes,
  animation,
}));
