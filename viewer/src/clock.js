// The page's clock. With a video the <video> element *is* the clock: the character is posed
// at video.currentTime, so picture and animation cannot drift apart. Without a playable
// video a timer over the take's duration stands in for it, with the same interface.

/** The source video as the clock. */
export class VideoClock {
  constructor(video) {
    this.video = video;
    this.kind = 'video';
  }

  get time() { return this.video.currentTime; }

  get paused() { return this.video.paused || this.video.ended; }

  play() { return this.video.play(); }

  pause() { this.video.pause(); }

  /** Seek to `t` seconds; resolves once the video shows the frame there. */
  seek(t) {
    const video = this.video;
    return new Promise((resolve) => {
      const done = () => {
        video.removeEventListener('seeked', done);
        resolve();
      };
      video.addEventListener('seeked', done);
      video.currentTime = t;
    });
  }
}

/** A stand-in clock for a take whose video is missing or cannot be decoded. */
export class TimerClock {
  constructor(duration) {
    this.duration = duration;
    this.kind = 'timer';
    this.origin = 0; // seconds at `start`
    this.start = null; // performance.now() when playing, else null
  }

  get time() {
    if (this.start === null) return this.origin;
    const t = this.origin + (performance.now() - this.start) / 1000;
    if (t < this.duration) return t;
    this.origin = this.duration; // stop at the end, as a video does
    this.start = null;
    return this.duration;
  }

  get paused() {
    return this.time >= this.duration || this.start === null;
  }

  play() {
    if (this.time >= this.duration) this.origin = 0;
    if (this.start === null) this.start = performance.now();
    return Promise.resolve();
  }

  pause() {
    this.origin = this.time;
    this.start = null;
  }

  seek(t) {
    this.origin = Math.min(Math.max(t, 0), this.duration);
    if (this.start !== null) this.start = performance.now();
    return Promise.resolve();
  }
}
