// keyshape viewer: the source video and the animated character side by side, in sync.
//
// The video is the clock. Playing, the character is posed at video.currentTime; paused, at
// the time of the frame shown, so a paused or scrubbed page shows exactly the weights of that
// frame in weights.csv. Frame f of the take is the video's picture at take.video_times[f] (its
// presentation time: a take tracked from --start 24 begins 24 frames into the video, a variable
// frame rate clip keeps its own timing); the animation starts at the take's first frame, so the
// character is posed at currentTime - video_times[0]. Without video_times, frame f is at f / fps.
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
  const source = Array.isArray(take.video_times) && take.video_times.length === take.n_frames
    ? take.video_times : null;
  const span = source ? source[lastFrame] - source[0] : lastFrame / fps;
  document.title = `keyshape · ${take.name}`;
  $('take').textContent = take.name;

  const [clock, character] = await Promise.all([
    openClock(take, span), Character.load(take.animation)]);
  // Clock seconds of frame f: the video's time of it, or (a timer) the animation's.
  const origin = source && clock.kind === 'video' ? 0 : (source ? source[0] : 0);
  const timeOf = (f) => (source ? source[f] - origin : f / fps);
  const animationTime = (t) => (source && clock.kind === 'video' ? t - source[0] : t);
  const frameAt = (t) => nearestFrame(timeOf, lastFrame, t);
  const stage = openStage(character);
  const panel = new WeightsPanel($('weights'), character.names,
    { frames: take.key_frames, regions: take.key_regions, descriptions: take.key_descriptions }, (f) => seekFrame(f));
  const slider = $('scrub');
  slider.max = String(lastFrame);

  let posedAt = null;
  let dragging = false;
  function update(force = false) {
    const frame = frameAt(clock.time);
    const animTime = animationTime(clock.paused ? timeOf(frame) : clock.time);
    if (force || animTime !== posedAt) {
      character.setTime(animTime);
      panel.update(character.values());
      posedAt = animTime;
    }
    if (!dragging) slider.value = String(frame);
    $('frame').textContent = `frame ${frame} / ${lastFrame}`;
    $('time').textContent = `${timeOf(frame).toFixed(3)} s`;
    $('play').textContent = clock.paused ? '▶ Play' : '❚❚ Pause';
    return frame;
  }

  async function seekFrame(frame) {
    const f = Math.min(Math.max(Math.round(frame), 0), lastFrame);
    // A hair past the frame's start time, so the decoder cannot land on the frame before.
    await clock.seek(timeOf(f) + Math.min(0.001, 0.25 / fps));
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

/** The frame whose time (timeOf, increasing) is nearest to t, in 0..lastFrame. */
function nearestFrame(timeOf, lastFrame, t) {
  let low = 0;
  let high = lastFrame;
  while (low < high) { // the first frame at or after t
    const mid = (low + high) >> 1;
    if (timeOf(mid) < t) low = mid + 1;
    else high = mid;
  }
  return low > 0 && t - timeOf(low - 1) < timeOf(low) - t ? low - 1 : low;
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
