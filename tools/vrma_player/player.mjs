// The VRM Animation player behind index.html: one avatar, one .vrma, the mixer set to a time.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VRMLoaderPlugin, VRMUtils } from "@pixiv/three-vrm";
import { VRMAnimationLoaderPlugin, VRMLookAtQuaternionProxy, createVRMAnimationClip } from "@pixiv/three-vrm-animation";

const SIZE = 256;
const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setSize(SIZE, SIZE);
renderer.setPixelRatio(1);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.add(new THREE.AmbientLight(0xffffff, 0.6));
const light = new THREE.DirectionalLight(0xffffff, 2.0);
light.position.set(0.3, 1.0, 2.0);
scene.add(light);
const camera = new THREE.PerspectiveCamera(30, 1, 0.01, 20);
let vrm = null;
let clip = null;
let mixer = null;

function newMixer() {
  // A fresh mixer: three.js's skips writing a value it wrote last time (after rest() an old mixer
  // would leave the expressions at rest), and a finished LoopOnce action no longer moves.
  if (mixer) mixer.uncacheRoot(vrm.scene);
  mixer = new THREE.AnimationMixer(vrm.scene);
  const action = mixer.clipAction(clip);
  action.setLoop(THREE.LoopOnce, 1); // the last frame at t = duration, not the first again
  action.clampWhenFinished = true;
  action.play();
}

function loader() {
  const gltf = new GLTFLoader();
  gltf.register((parser) => new VRMLoaderPlugin(parser));
  gltf.register((parser) => new VRMAnimationLoaderPlugin(parser));
  return gltf;
}

// Load the avatar and the animation; frame the camera on `focus` ([x, y, z], metres) from `distance`.
window.load = async (avatarUrl, vrmaUrl, focus, distance) => {
  const avatar = await loader().loadAsync(avatarUrl);
  vrm = avatar.userData.vrm;
  if (!vrm) throw new Error(`${avatarUrl}: three-vrm found no VRM in it`);
  VRMUtils.rotateVRM0(vrm); // a VRM 0.x avatar faces -Z: turned to face +Z as 1.0 does
  if (vrm.lookAt) {
    const proxy = new VRMLookAtQuaternionProxy(vrm.lookAt);
    proxy.name = "lookAtQuaternionProxy";
    vrm.scene.add(proxy);
  }
  scene.add(vrm.scene);
  const animation = await loader().loadAsync(vrmaUrl);
  const animations = animation.userData.vrmAnimations;
  if (!animations || !animations.length) throw new Error(`${vrmaUrl}: three-vrm-animation found no VRM Animation`);
  clip = createVRMAnimationClip(animations[0], vrm);
  newMixer();
  camera.position.set(focus[0], focus[1], focus[2] + distance);
  camera.lookAt(focus[0], focus[1], focus[2]);
  return {
    metaVersion: vrm.meta.metaVersion,
    duration: clip.duration,
    tracks: clip.tracks.map((track) => track.name),
    expressions: vrm.expressionManager.expressions.map((e) => e.expressionName),
  };
};

// Set the animation to time t (seconds), render, and report the expressions' weights, every morph
// target's influence and the head bone's rotation.
window.pose = (t) => {
  newMixer(); // a played-out LoopOnce action stays paused: each pose starts from a new one
  mixer.setTime(t);
  vrm.update(0);
  renderer.render(scene, camera);
  const weights = {};
  for (const e of vrm.expressionManager.expressions) weights[e.expressionName] = e.weight;
  const morphs = {};
  vrm.scene.traverse((node) => {
    if (node.isMesh && node.morphTargetInfluences) {
      const names = node.morphTargetDictionary || {};
      for (const [name, index] of Object.entries(names)) morphs[`${node.name}/${name}`] = node.morphTargetInfluences[index];
    }
  });
  const head = vrm.humanoid.getNormalizedBoneNode("head");
  const look = vrm.lookAt ? [vrm.lookAt.yaw, vrm.lookAt.pitch] : null;
  return { weights, morphs, head: head ? head.quaternion.toArray() : null, look };
};
window.ready = true;

// The avatar at rest: no expression, no bone turned (what a shut, neutral face looks like).
window.rest = () => {
  vrm.expressionManager.resetValues();
  vrm.humanoid.resetNormalizedPose();
  vrm.update(0);
  renderer.render(scene, camera);
};
