// Drawing the character: a WebGL renderer, a camera framed on the neutral face (of a full-body
// avatar too: Character.faceBox), soft lights
// and orbit controls (drag to turn, wheel to zoom).

import * as THREE from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';

export class Stage {
  constructor(canvas, character) {
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x1d2026);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x30343c, 2.0));
    const key = new THREE.DirectionalLight(0xffffff, 2.2);
    key.position.set(0.4, 0.6, 1.0);
    this.scene.add(key);
    this.scene.add(character.scene);
    this.camera = new THREE.PerspectiveCamera(30, 1, 0.001, 100);
    this.controls = new OrbitControls(this.camera, canvas);
    this.resize();
    this.frame(character.faceBox());
    new ResizeObserver(() => this.resize()).observe(canvas.parentElement);
  }

  /**
   * Put the whole box in view, seen from the front (+Z, glTF's "toward the viewer"): its height,
   * or its width where the pane is narrower, fills the pane but for a margin.
   */
  frame(box) {
    const size = box.getSize(new THREE.Vector3());
    const centre = box.getCenter(new THREE.Vector3());
    const half = 1.15 * Math.max(size.y / 2, size.x / 2 / this.camera.aspect, 1e-3);
    const distance = half / Math.tan(THREE.MathUtils.degToRad(this.camera.fov / 2)) + size.z / 2;
    this.camera.position.copy(centre).add(new THREE.Vector3(0, 0, distance));
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.controls.target.copy(centre);
    this.controls.update();
  }

  resize() {
    const pane = this.renderer.domElement.parentElement;
    const width = Math.max(pane.clientWidth, 1);
    const height = Math.max(pane.clientHeight, 1);
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }
}
