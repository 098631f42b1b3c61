// The animated character: a .glb as keyshape writes it (one mesh with named morph targets on
// node "face", one animation with a `weights` channel and a head `rotation` channel), posed
// at any time by sampling the glTF animation directly (the same interpolants and property
// bindings three.js's AnimationMixer uses, without its looping and blending state).

import { Box3, PropertyBinding, Vector3 } from 'three';
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

  /**
   * The face's box in the world at rest: the vertices the morph targets move and every vertex
   * near them (within 1.3 times the farthest moved one's distance from their centre), so a
   * full-body avatar gives its head and hair, not its T-posed body.
   */
  faceBox() {
    this.scene.updateMatrixWorld(true);
    const moved = [];
    const all = [];
    this.scene.traverse((object) => {
      if (!object.isMesh || !object.geometry.getAttribute('position')) return;
      if (object.isSkinnedMesh) object.skeleton.update();
      const morphs = object.geometry.morphAttributes.position || [];
      const count = object.geometry.getAttribute('position').count;
      for (let i = 0; i < count; i++) {
        const point = object.getVertexPosition(i, new Vector3()).applyMatrix4(object.matrixWorld);
        all.push(point);
        if (morphs.some((m) => Math.abs(m.getX(i)) + Math.abs(m.getY(i)) + Math.abs(m.getZ(i)) > 1e-6)) {
          moved.push(point);
        }
      }
    });
    const box = new Box3().setFromPoints(moved.length ? moved : all);
    if (!moved.length) return box;
    const centre = box.getCenter(new Vector3());
    const reach = 1.3 * Math.max(...moved.map((p) => p.distanceTo(centre)));
    return new Box3().setFromPoints(all.filter((p) => p.distanceTo(centre) <= reach));
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
