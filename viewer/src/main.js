// keyshape viewer: the source video and the animated character side by side, in sync.
//
// The video is the clock. Playing, the character is posed at video.currentTime; paused, at
// the time of the frame shown, frame / fps with frame = round(currentTime * fps), so a paused
// or scrubbed page shows exactly the weights of that frame in weights.csv.
//
// window.keyshape is a small hook for tests and scripts (see `hook` below).

import { Character } from './character.js';
import { TimerClock, VideoClock } from './clock.js';
import { runLive } from './live.js';
import { WeightsPanel } from './panel.js';
import { Stage } from './stage.js';

const $ = (id) => document.getElementById(id);

const hook = { ready: false, error: null };
window.keyshape = hook;

async function main() {
  const take = await fetchJson('/api/take');
  if (take.live) return runLive(take, hook, $, notice); // keyshape live --view
  const fps = take.fps;
  const lastFrame = take.n_frames - 1;
  const frameAt = (t) => Math.min(Math.max(Math.round(t * fps), 0), lastFrame);
  document.title = `keyshape · ${take.name}`;
  $('take').textContent = take.name;

  const [clock, character] = await Promise.all([
    openClock(take, lastFrame / fps), Character.load(take.animation)]);
  const stage = openStage(character);
  const panel = new WeightsPanel($('weights'), character.names, take.key_frames, (f) => seekFrame(f));
  const slider = $('scrub');
  slider.max = String(lastFrame);

  let posedAt = null;
  let dragging = false;
  function update(force = false) {
    const frame = frameAt(clock.time);
    const animTime = clock.paused ? frame / fps : clock.time;
    if (force || animTime !== posedAt) {
      character.setTime(animTime);
      panel.update(character.values());
      posedAt = animTime;
    }
    if (!dragging) slider.value = String(frame);
    $('frame').textContent = `frame ${frame} / ${lastFrame}`;
    $('time').textContent = `${(frame / fps).toFixed(3)} s`;
    $('play').textContent = clock.paused ? '▶ Play' : '❚❚ Pause';
    return frame;
  }

  async function seekFrame(frame) {
    const f = Math.min(Math.max(Math.round(frame), 0), lastFrame);
    // A hair past the frame's start time, so the decoder cannot land on the frame before.
    await clock.seek(f / fps + Math.min(0.001, 0.25 / fps));
    return update(true);
  }

  async function play() {
    if (frameAt(clock.time) >= lastFrame) await seekFrame(0);
    await clock.play();
    update(true);
  }

  function pause() {
    clock.pause();
    return update(true);
  }

  $('play').addEventListener('click', () => (clock.paused ? play() : pause()));
  slider.addEventListener('pointerdown', () => { dragging = true; });
  slider.addEventListener('pointerup', () => { dragging = false; });
  slider.addEventListener('input', () => seekFrame(Number(slider.value)));
  $('sound').addEventListener('change', (e) => { $('video').muted = !e.target.checked; });
  document.addEventListener('keydown', (e) => {
    if (e.target instanceof HTMLInputElement && e.target.type !== 'range') return;
    const frame = frameAt(clock.time);
    const keys = {
      ' ': () => (clock.paused ? play() : pause()),
      ArrowLeft: () => { pause(); seekFrame(frame - 1); },
      ArrowRight: () => { pause(); seekFrame(frame + 1); },
      Home: () => seekFrame(0),
      End: () => seekFrame(lastFrame),
    };
    if (keys[e.key]) {
      e.preventDefault();
      keys[e.key]();
    }
  });

  const loop = () => {
    update();
    if (stage) stage.render();
    requestAnimationFrame(loop);
  };
  await seekFrame(0);
  requestAnimationFrame(loop);

  Object.assign(hook, {
    fps,
    nFrames: take.n_frames,
    names: character.names.slice(),
    clock: clock.kind,
    webgl: stage !== null,
    /** Frame shown now: round(time * fps). */
    frame: () => frameAt(clock.time),
    /** Clock time in seconds (video.currentTime when there is a video). */
    time: () => clock.time,
    paused: () => clock.paused,
    play,
    pause,
    /** Go to a frame; resolves to the frame shown once the video has seeked. */
    seek: seekFrame,
    /** {morph target name: influence} of the character now. */
    influences: () => character.influences(),
    /** Head rotation quaternion [x, y, z, w] of the character now. */
    rotation: () => character.rotation(),
    ready: true,
  });
}

async function fetchJson(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return response.json();
}

/** The video as the clock once it can show frames; a timer if it is missing or unplayable. */
async function openClock(take, duration) {
  const video = $('video');
  if (!take.video) {
    notice(`No source video found: the character plays on its own.`);
    return new TimerClock(duration);
  }
  $('video-name').textContent = take.video_name;
  const loaded = new Promise((resolve, reject) => {
    video.addEventListener('loadeddata', resolve, { once: true });
    video.addEventListener('error', () => reject(video.error), { once: true });
  });
  video.src = take.video;
  try {
    await loaded;
    return new VideoClock(video);
  } catch (error) {
    notice(`This browser cannot play ${take.video_name}` +
           ` (${error && error.message ? error.message : 'unsupported format'}):` +
           ' the character plays on its own.');
    video.removeAttribute('src');
    return new TimerClock(duration);
  }
}

function openStage(character) {
  try {
    return new Stage($('scene'), character);
  } catch (error) {
    notice(`WebGL is not available, so the character cannot be drawn (${error.message});` +
           ' the weights still play.');
    return null;
  }
}

function notice(text) {
  const box = $('notice');
  box.textContent = text;
  box.hidden = false;
}

main().catch((error) => {
  hook.error = String(error && error.message ? error.message : error);
  notice(`The viewer could not start: ${hook.error}`);
  console.error(error);
});
