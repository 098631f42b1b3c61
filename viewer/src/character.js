// The animated character: a .glb as keyshape writes it (one mesh with named morph targets on
// node "face", one animation with a `weights` channel and a head `rotation` channel), posed
// at any time by sampling the glTF animation directly (the same interpolants and property
// bindings three.js's AnimationMixer uses, without its looping and blending state).

import { PropertyBinding } from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';

export class Character {
  /** Load the .glb at `url`. */
  static async load(url) {
    const gltf = await new GLTFLoader().loadAsync(url);
    return new Character(gltf);
  }

  constructor(gltf) {
    this.scene = gltf.scene;
    this.meshes = [];
    this.scene.traverse((object) => {
      if (object.isMesh && object.morphTargetInfluences) this.meshes.push(object);
    });
    if (this.meshes.length === 0) throw new Error('the .glb has no mesh with morph targets');
    this.mesh = this.meshes[0];
    this.names = targetNames(this.mesh);
    this.head = this.scene.getObjectByName('face') || this.mesh;
    const clip = gltf.animations[0];
    if (!clip) throw new Error('the .glb has no animation');
    this.duration = clip.duration;
    this.channels = clip.tracks.map((track) => ({
      interpolant: track.createInterpolant(),
      binding: PropertyBinding.create(this.scene, track.name),
    }));
  }

  /** Pose the character at `t` seconds of its animation (clamped to the animation). */
  setTime(t) {
    const time = Math.min(Math.max(t, 0), this.duration);
    for (const { interpolant, binding } of this.channels) {
      binding.setValue(interpolant.evaluate(time), 0);
    }
    this.scene.updateMatrixWorld(true);
  }

  /** Set the influences of the targets named in `names` to `values` (live mode); others keep theirs. */
  setInfluences(names, values) {
    for (const mesh of this.meshes) {
      const index = mesh.morphTargetDictionary || {};
      names.forEach((name, i) => {
        const k = index[name];
        if (k !== undefined) mesh.morphTargetInfluences[k] = values[i];
      });
    }
  }

  /** Turn the head node to the quaternion [x, y, z, w] (live mode). */
  setRotation(q) {
    this.head.quaternion.fromArray(q);
    this.scene.updateMatrixWorld(true);
  }

  /** Current influence of each morph target, in target order. */
  values() {
    return Array.from(this.mesh.morphTargetInfluences);
  }

  /** Current influences as {target name: value}. */
  influences() {
    const out = {};
    this.names.forEach((name, i) => { out[name] = this.mesh.morphTargetInfluences[i]; });
    return out;
  }

  /** The head node's rotation as a quaternion [x, y, z, w]. */
  rotation() {
    return this.head.quaternion.toArray();
  }
}

/** Target names in index order: from morphTargetDictionary (mesh.extras.targetNames). */
function targetNames(mesh) {
  const names = mesh.morphTargetInfluences.map((_, i) => `target_${i}`);
  for (const [name, index] of Object.entries(mesh.morphTargetDictionary || {})) names[index] = name;
  return names;
}
