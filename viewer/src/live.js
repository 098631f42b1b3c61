// Live mode (keyshape live --view): the camera and the character as the session solves them.
//
// The page's WebSocket (/live) brings a JSON message per solved frame ({frame, time, face,
// names, weights, head}) and, a few times a second, the camera picture as a JPEG (drawn on a
// canvas, which keeps the last picture until the next is decoded). The
// character's morph targets are set by name from the weights, its head node from `head`.

import { Character } from './character.js';
import { WeightsPanel } from './panel.js';
import { Stage } from './stage.js';

export async function runLive(take, hook, $, notice) {
  document.title = `keyshape · live · ${take.name}`;
  document.body.classList.add('live');
  $('take').textContent = `live: ${take.name}`;
  $('video').hidden = true;
  const camera = $('camera');
  camera.hidden = false;
  $('video-name').textContent = 'camera';

  const character = await Character.load(take.animation);
  let stage = null;
  try {
    stage = new Stage($('scene'), character);
  } catch (error) {
    notice(`WebGL is not available, so the character cannot be drawn (${error.message}); the weights still show.`);
  }
  const panel = new WeightsPanel($('weights'), character.names,
    { regions: take.key_regions, descriptions: take.key_descriptions }, () => {});
  const state = { frames: 0, images: 0, frame: -1, time: 0, face: false, open: false, closed: false };

  const socket = new WebSocket(`ws://${window.location.host}${take.socket}`);
  socket.binaryType = 'blob';
  socket.addEventListener('open', () => { state.open = true; });
  socket.addEventListener('close', () => {
    state.closed = true;
    notice('The live session has ended.');
  });
  const picture = camera.getContext('2d');
  let drawing = false;
  socket.addEventListener('message', (event) => {
    if (typeof event.data === 'string') {
      const message = JSON.parse(event.data);
      character.setInfluences(message.names, message.weights);
      if (message.head) character.setRotation(message.head);
      panel.update(character.values());
      Object.assign(state, { frame: message.frame, time: message.time, face: message.face });
      state.frames += 1;
      $('frame').textContent = `frame ${message.frame}`;
      $('time').textContent = `${message.time.toFixed(3)} s${message.face ? '' : ' (no face)'}`;
    } else if (!drawing) { // a JPEG of the camera; one decoded at a time, the newest wins
      drawing = true;
      createImageBitmap(event.data).then((bitmap) => {
        if (camera.width !== bitmap.width || camera.height !== bitmap.height) {
          [camera.width, camera.height] = [bitmap.width, bitmap.height];
        }
        picture.drawImage(bitmap, 0, 0);
        bitmap.close();
        state.images += 1;
      }).catch(() => {}).finally(() => { drawing = false; });
    }
  });

  const loop = () => {
    if (stage) stage.render();
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);

  Object.assign(hook, {
    live: true,
    names: character.names.slice(),
    webgl: stage !== null,
    /** Frames received so far, camera pictures received so far. */
    frames: () => state.frames,
    images: () => state.images,
    /** Source frame number and media time of the last frame received; whether it had a face. */
    frame: () => state.frame,
    time: () => state.time,
    face: () => state.face,
    connected: () => state.open && !state.closed,
    /** {morph target name: influence} of the character now. */
    influences: () => character.influences(),
    /** Head rotation quaternion [x, y, z, w] of the character now. */
    rotation: () => character.rotation(),
    ready: true,
  });
}
