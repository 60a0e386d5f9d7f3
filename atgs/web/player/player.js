// The player page: wires the stream, the view camera and the renderer to the controls of
// index.html, plays the frames in time, and exposes the small test API (Player.api below).

import { ViewCamera, fitIntrinsics, upDirection } from './camera.js';
import { attachControls, fillHelp } from './controls.js';
import { Renderer } from './renderer.js';
import { openStream } from './streams.js';

const SPEEDS = [0.25, 0.5, 1, 1.5, 2];
// How long a lost WebGL context may stay lost before the page says so (browsers restore within a second or two).
const CONTEXT_RESTORE_WAIT_MS = 10000;

/**
 * The page's options from its URL parameters (docs/web.md):
 * stream (folder, default "stream/"), frame (exported frame index, 0), camera (training camera
 * index; default the first held-out one, else 0), paused=1, size=camera, budget (MB of chunks
 * held at most, decoded and compressed; default stream.js's), ahead (compressed chunks held at
 * most, the playing one included). A malformed value is reported in `error` (the player shows it) rather than thrown,
 * so the page still comes up.
 * @param {URLSearchParams} params
 */
export function pageOptions(params) {
  let error = null;
  const integer = (name) => {
    if (!params.has(name)) return null;
    const v = Number(params.get(name));
    if (Number.isInteger(v) && v >= 0) return v;
    error ??= `URL parameter ${name}=${params.get(name)} is not a non-negative integer`;
    return null;
  };
  const positive = (name) => {
    if (!params.has(name)) return null;
    const v = Number(params.get(name));
    if (v > 0 && Number.isFinite(v)) return v;
    error ??= `URL parameter ${name}=${params.get(name)} is not a positive number`;
    return null;
  };
  const ahead = integer('ahead');
  if (ahead === 0) error ??= 'URL parameter ahead=0: the player holds at least the chunk it plays (ahead=1)';
  const budget = positive('budget');
  return {
    stream: params.get('stream') || 'stream/',
    frame: integer('frame') ?? 0,
    camera: integer('camera'),
    paused: params.get('paused') === '1',
    cameraSize: params.get('size') === 'camera',
    budgetBytes: budget === null ? null : budget * 1e6,
    maxChunks: ahead || null,
    error,
  };
}

function megabytes(bytes) {
  return (bytes / 1e6).toFixed(bytes < 1e7 ? 2 : 1);
}

export class Player {
  /**
   * @param {Document} doc the page (index.html's elements by id)
   * @param {ReturnType<typeof pageOptions>} options
   */
  constructor(doc, options) {
    this.doc = doc;
    this.options = options;
    const $ = (id) => doc.getElementById(id);
    this.el = {
      canvas: $('view'), error: $('error'), status: $('status'), play: $('play'), scrub: $('scrub'),
      readout: $('readout'), loop: $('loop'), speed: $('speed'), camera: $('camera'),
      progress: $('progress'), progressText: $('progress-text'), help: $('help'), helpKeys: $('help-keys'),
      note: $('note'),
    };
    this.stream = null;
    this.renderer = null;
    this.view = null;
    this.homeCamera = 0;            // the training camera last chosen: where resetView returns
    this.manifest = null;
    this.error = null;              // the error line as shown now (null: hidden)
    this.fatal = null;              // the error that stopped the player (the first stays)
    this.failures = new Map();      // stream file (window item) -> {message, retryAt}: failed, until it loads
    this.note = null;               // a one-line note of something the page works around (no environment map)
    this.retrying = null;           // the status line while a download is retried
    this.contextLost = false;
    this.contextRestores = 0;
    this.contextTimer = null;
    this.stopped = false;           // after a fatal error: nothing more is drawn
    this.playing = !options.paused;
    this.position = options.frame;  // playback position in exported frames (fractional while playing)
    this.frame = -1;                // the exported frame drawn last
    this.buffering = false;
    this.drawnKey = null;           // what the last draw showed (frame, camera version, canvas size)
    this.forceDraw = false;
    this.last = null;               // {chunk, local, view} of the last draw, for readPixels
    this.framesDrawn = 0;
    this.drawTimes = [];
    this.firstFrameMs = null;
    this.lastTick = null;
    this.waiters = [];              // {test(frame), resolve, reject}: promises of the test API
  }

  /** Loads the stream and starts drawing; every failure ends in showError. */
  async start() {
    try {
      if (this.options.error) throw new Error(this.options.error);
      if (this.doc.location?.protocol === 'file:') {
        throw new Error('this page was opened from a file: browsers refuse to load the stream that way; '
          + 'serve the folder (atgs-serve DIR, or python -m http.server in it) and open its http:// address');
      }
      this.renderer = new Renderer(this.el.canvas);
      this.renderer.onContextLost = () => this._contextLost();
      this.renderer.onContextRestored = () => this._contextRestored();
      // a Gaussian chunk stream or the model itself, as the manifest says (streams.js); both
      // hold their files in the same byte budget and fetch them with the same retries
      this.stream = await openStream(this.options.stream, this.renderer.gl, {
        budgetBytes: this.options.budgetBytes ?? undefined,
        maxChunks: this.options.maxChunks ?? undefined,
        onProgress: (buffered, wanted) => this._showProgress(buffered, wanted),
        onRetry: (file, attempt, delay, e) => {
          this.retrying = `connection trouble (${e.message}): trying ${file} again in ${(delay / 1000).toFixed(1)} s…`;
        },
        onChunkLoaded: (item) => { this.retrying = null; this._fileLoaded(item); },
        // a file's failure leaves the others playable; the manifest's (also rejecting openStream)
        // and the model decode's stop the player
        onError: (e, item, retryAt) => (item === undefined ? this.showError(e.message) : this._fileFailed(item, e, retryAt)),
      });
      const manifest = this.stream.manifest;
      this.manifest = manifest;
      if (this.options.budgetBytes !== null && this.stream.budgetBytes > this.options.budgetBytes) {
        this.showNote(`URL parameter budget=${this.options.budgetBytes / 1e6}: this stream needs ${megabytes(this.stream.budgetBytes)} MB `
          + 'to play without stalls (what the unit playing and the next need, downloaded and decoded): holding that');
      }
      this.renderer.configure(manifest);
      this._setupControls(manifest);
      this._setupView(manifest);
      if (manifest.environment) await this._loadEnvironment(manifest.environment);
      this._requestFrame(this.options.frame);
      this.doc.defaultView.requestAnimationFrame((t) => this._tick(t));
    } catch (e) {
      this.showError(e.message);
    }
  }

  /**
   * Shows a one-line error that stops the player (no manifest, no WebGL2, a bad URL parameter);
   * the first one stays.
   */
  showError(message) {
    this.fatal ??= String(message).split('\n')[0];
    this._showErrorLine();
    if (!this.stopped) {
      this.stopped = true;
      this._halt(new Error(this.fatal));
    }
  }

  // A stream file's download failed (its retries spent, or a corrupt file): the error line says
  // so until it loads, and when it is tried again. The frames of the other files still play;
  // playback waits where it reaches a file that is tried again later, stops at one that is not.
  _fileFailed(item, error, retryAt) {
    this.retrying = null;  // the fetcher's retries are over: the error line says what comes next
    this.failures.set(item, { message: String(error.message).split('\n')[0], retryAt });
    this._showErrorLine();
  }

  _fileLoaded(item) {
    if (this.failures.delete(item)) this._showErrorLine();
  }

  // The error line: the fatal error, else the oldest failure still standing with when it is tried
  // again (a countdown, refreshed every tick), else hidden.
  _showErrorLine() {
    let text = this.fatal;
    const failure = this.failures.values().next().value;
    if (text === null && failure) {
      const wait = failure.retryAt - performance.now();
      if (failure.retryAt === Infinity) text = failure.message;
      else text = `${failure.message}: ${wait > 0 ? `trying again in ${Math.ceil(wait / 1000)} s` : 'trying again'}…`;
    }
    if (text === this.error) return;
    this.error = text;
    this.el.error.textContent = text ?? '';
    this.el.error.hidden = text === null;
  }

  /** Shows a one-line note (not an error: the page plays on); the first one stays. */
  showNote(message) {
    if (this.note) return;
    this.note = String(message).split('\n')[0];
    this.el.note.textContent = this.note;
    this.el.note.hidden = false;
  }

  // A lost WebGL context: nothing is drawn until the browser restores it, then the frame is drawn again.
  _contextLost() {
    this.contextLost = true;
    this.el.status.textContent = 'the graphics context was lost: waiting for the browser to restore it…';
    clearTimeout(this.contextTimer);
    this.contextTimer = setTimeout(() => {
      if (this.contextLost) this.showError('the WebGL context was lost and the browser did not restore it: reload the page');
    }, CONTEXT_RESTORE_WAIT_MS);
  }

  _contextRestored() {
    clearTimeout(this.contextTimer);
    this.contextLost = false;
    this.contextRestores++;
    this.stream?.contextRestored();  // a model stream's decoder lived on the lost context
    this.el.status.textContent = '';
    this.forceDraw = true;
  }

  // Stops playing and fails the test API's waiters: what they wait for cannot be drawn.
  _halt(error) {
    this.playing = false;
    this.buffering = false;
    this.el.status.textContent = '';
    this._showPlaying();
    for (const w of this.waiters) w.reject(error);
    this.waiters = [];
  }

  // --- setup -----------------------------------------------------------------------------
  _setupControls(manifest) {
    const { play, scrub, loop, speed, camera } = this.el;
    const n = manifest.frames.length;
    if (this.options.frame >= n) throw new Error(`URL parameter frame=${this.options.frame}: the stream has ${n} frames (0..${n - 1})`);
    scrub.max = String(n - 1);
    // dragging moves the playhead; letting go asks for the frame (a failed file there is fetched
    // again once, not at every step of the drag)
    scrub.addEventListener('input', () => this._requestFrame(Number(scrub.value), false));
    scrub.addEventListener('change', () => this._requestFrame(Number(scrub.value)));
    scrub.addEventListener('pointerdown', () => this._pauseWhileScrubbing());
    play.addEventListener('click', () => (this.playing ? this.pause() : this.play()));
    loop.checked = true;
    loop.addEventListener('change', () => this.stream.setWrap(loop.checked));  // no look-ahead past the end without loop
    for (const s of SPEEDS) speed.add(new Option(`${s}x`, String(s), s === 1, s === 1));
    camera.add(new Option('free', 'free'));
    manifest.cameras.forEach((c, i) => camera.add(new Option(`${c.name}${c.held_out ? ' (held out)' : ''}`, String(i))));
    camera.addEventListener('change', () => {
      if (camera.value !== 'free') this.setCamera(Number(camera.value));
    });
    fillHelp(this.el.helpKeys);
    this._showPlaying();
  }

  // Playback holds while the scrub bar is dragged and goes on from where it is let go (not at the
  // end of a video that does not loop), as a video player's does.
  _pauseWhileScrubbing() {
    if (!this.playing) return;
    this.pause();
    const win = this.doc.defaultView;
    const resume = () => {
      win.removeEventListener('pointerup', resume);
      win.removeEventListener('pointercancel', resume);
      if (this.el.loop.checked || Math.floor(this.position) < this.manifest.frames.length - 1) this.play();
    };
    win.addEventListener('pointerup', resume);
    win.addEventListener('pointercancel', resume);
  }

  _setupView(manifest) {
    const cams = manifest.cameras;
    if (cams.length === 0) throw new Error(`${this.stream.url('manifest.json')} lists no cameras`);
    const scene = manifest.scene ?? {};
    this.view = new ViewCamera({ center: scene.center ?? [0, 0, 0], radius: scene.radius ?? 1, up: upDirection(cams) });
    let index = this.options.camera;
    if (index === null) index = Math.max(0, cams.findIndex((c) => c.held_out));
    if (index >= cams.length) throw new Error(`URL parameter camera=${index}: the stream has ${cams.length} cameras (0..${cams.length - 1})`);
    const canvas = this.el.canvas;
    if (this.options.cameraSize) {
      canvas.classList.add('camera-size');  // sized by setCamera
    } else {
      const fit = () => {
        const dpr = this.doc.defaultView.devicePixelRatio || 1;
        canvas.width = Math.max(1, Math.round(canvas.clientWidth * dpr));
        canvas.height = Math.max(1, Math.round(canvas.clientHeight * dpr));
      };
      fit();
      new ResizeObserver(fit).observe(canvas);
    }
    this.setCamera(index);
    attachControls(canvas, this._commands());
  }

  // What the pointer, wheel and keys do (controls.js): view moves make the camera menu "free".
  _commands() {
    const free = () => { this.el.camera.value = 'free'; };
    const n = this.manifest.frames.length, cams = this.manifest.cameras.length;
    const speed = this.el.speed;
    return {
      orbit: (yaw, pitch) => { this.view.orbit(yaw, pitch); free(); },
      pan: (dx, dy) => { this.view.pan(dx, dy, this._intrinsics()); free(); },
      zoom: (factor) => { this.view.zoom(factor); free(); },
      togglePlay: () => (this.playing ? this.pause() : this.play()),
      step: (frames) => {
        this.pause();
        this._requestFrame(Math.min(n - 1, Math.max(0, Math.floor(this.position) + frames)));
      },
      seekFraction: (f) => this._requestFrame(Math.round(f * (n - 1))),
      toggleLoop: () => { this.el.loop.checked = !this.el.loop.checked; this.stream.setWrap(this.el.loop.checked); },
      changeSpeed: (d) => { speed.selectedIndex = Math.min(speed.length - 1, Math.max(0, speed.selectedIndex + d)); },
      resetView: () => this.setCamera(this.homeCamera),
      changeCamera: (d) => this.setCamera((((this.view.trainingIndex ?? this.homeCamera) + d) % cams + cams) % cams),
      toggleHelp: () => { this.el.help.open = !this.el.help.open; },
    };
  }

  // The background by direction; without it (missing, unreadable) the trained background colour,
  // with a note: a wrong background is better than no video.
  async _loadEnvironment(env) {
    const where = this.stream.url(env.file);
    let image;
    try {
      const bytes = await this.stream.fetchFile(env.file);
      try {
        image = await createImageBitmap(new Blob([bytes]), { colorSpaceConversion: 'none', premultiplyAlpha: 'none' });
      } catch (e) {
        throw new Error(`${where} is not a readable image (${e.message})`);
      }
    } catch (e) {
      this.showNote(`${e.message}: drawing over the background colour instead`);
      return;
    }
    this.renderer.setEnvironment(image, env.basis);
  }

  // --- playing ---------------------------------------------------------------------------
  /** Start playing from the current frame (asked for: a failed file of it is fetched again now). */
  play() {
    if (this.stopped || !this.manifest) return;
    if (!this.el.loop.checked && Math.floor(this.position) >= this.manifest.frames.length - 1) this.position = 0;
    this.playing = true;
    this._showPlaying();
    this.stream.setPlayhead(this.stream.locate(Math.floor(this.position)).chunk, true);
  }

  /** Stop at the current frame. */
  pause() {
    this.playing = false;
    if (this.frame >= 0) this.position = this.frame;
    this._showPlaying();
  }

  /**
   * Show training camera i exactly: its pose, and its intrinsics fitted to the canvas (with
   * size=camera the canvas takes the camera's pixel size, CSS size equal, no devicePixelRatio).
   */
  setCamera(i) {
    if (!this.view) throw new Error('the stream is not loaded yet');
    const cams = this.manifest.cameras;
    if (!Number.isInteger(i) || i < 0 || i >= cams.length) throw new RangeError(`camera ${i}: the stream has ${cams.length} cameras`);
    this.view.setTraining(cams[i], i);
    this.homeCamera = i;
    this.el.camera.value = String(i);
    if (this.options.cameraSize) {
      const canvas = this.el.canvas;
      canvas.width = cams[i].width;
      canvas.height = cams[i].height;
      canvas.style.width = `${canvas.width}px`;
      canvas.style.height = `${canvas.height}px`;
    }
  }

  // Go to frame i; `asked`: the viewer asked for it (a seek): a failed file of it is fetched again now.
  _requestFrame(i, asked = true) {
    this.position = i;
    this.forceDraw = true;
    if (this.stream?.manifest) this.stream.setPlayhead(this.stream.locate(i).chunk, asked);
  }

  _intrinsics() {
    return fitIntrinsics(this.view.intrinsics, this.el.canvas.width, this.el.canvas.height);
  }

  _tick(now) {
    const win = this.doc.defaultView;
    if (this.stopped) return;
    // seconds since the last tick, at most one: a hidden tab gets no ticks and must not jump on return
    const dt = this.lastTick === null ? 0 : Math.min(1, (now - this.lastTick) / 1000);
    this.lastTick = now;
    const n = this.manifest.frames.length;
    if (this.playing && !this.buffering) {
      this.position += dt * this.manifest.fps * Number(this.el.speed.value);
      if (this.position >= n) {
        if (this.el.loop.checked) {
          this.position %= n;
        } else {
          this.position = n - 1;
          this.pause();
        }
      }
    }
    const want = Math.floor(this.position);
    const { chunk: ci, local } = this.stream.locate(want);
    if (ci !== this.stream.playhead) this.stream.setPlayhead(ci);  // load from here on
    const chunk = this.stream.decodedNow(ci);
    const failure = this.stream.failure(ci);
    if (failure?.retryAt === Infinity) {  // broken until asked for again (a seek, Play)
      if (this.playing || this.buffering || this.waiters.length) this._halt(failure.error);
      this.position = want;
    } else if (!chunk) {
      // wait for the frame, never skip it: playback holds here until its chunk is decoded (or,
      // after a failure that may pass, fetched again: the error line counts down to it)
      this.buffering = true;
      this.position = want;
      if (!failure) this.stream.chunk(ci).then(() => { this.forceDraw = true; }, () => {});
      this.el.status.textContent = this.retrying ?? (this.framesDrawn ? 'buffering…' : 'loading…');
    } else {
      if (this.el.status.textContent && !this.contextLost) this.el.status.textContent = '';
      this.buffering = false;
      this._draw(want, chunk, local);
      const chunks = this.stream.units;
      if (this.playing && chunks > 1 && (ci + 1 < chunks || this.el.loop.checked)) {
        this.stream.chunk((ci + 1) % chunks).catch(() => {});  // inflate the next chunk before it is needed
      }
    }
    if (this.failures.size) this._showErrorLine();  // the countdown
    win.requestAnimationFrame((t) => this._tick(t));
  }

  _draw(i, chunk, local) {
    const canvas = this.el.canvas;
    const key = `${i} ${this.view.version} ${canvas.width}x${canvas.height}`;
    if (key === this.drawnKey && !this.forceDraw) return;
    const view = { w2c: this.view.w2c, intr: this._intrinsics() };
    if (!this.renderer.draw(chunk, local, view)) return;  // the context is lost: drawn once it is back
    this.last = { chunk, local, view: { w2c: Float64Array.from(view.w2c), intr: view.intr } };
    this.drawnKey = key;
    this.forceDraw = false;
    this.frame = i;
    this.framesDrawn++;
    const now = performance.now();
    if (this.firstFrameMs === null) this.firstFrameMs = now;
    this.drawTimes.push(now);
    while (this.drawTimes.length > 2 && now - this.drawTimes[0] > 2000) this.drawTimes.shift();
    this._showFrame(i);
    const pending = this.waiters;
    this.waiters = pending.filter((w) => !w.test(i));
    for (const w of pending) if (w.test(i)) w.resolve();
  }

  // --- controls --------------------------------------------------------------------------
  _showPlaying() {
    this.el.play.textContent = this.playing ? 'Pause' : 'Play';
    this.el.play.setAttribute('aria-pressed', String(this.playing));
  }

  _showFrame(i) {
    const m = this.manifest;
    this.el.scrub.value = String(i);
    this.el.readout.textContent = `frame ${i} / ${m.frames.length - 1} (model frame ${m.frames[i]}) · ${(i / m.fps).toFixed(2)} s`;
  }

  // The look-ahead window's bytes held of those it wants (not the whole video: it never is in memory).
  _showProgress(buffered, wanted) {
    this.el.progress.max = Math.max(1, wanted);
    this.el.progress.value = buffered;
    this.el.progressText.textContent = `${megabytes(buffered)} MB buffered`;
  }

  _whenDrawn(test) {
    if (this.stopped) return Promise.reject(new Error(this.fatal));
    return new Promise((resolve, reject) => this.waiters.push({ test, resolve, reject }));
  }

  _drawFps() {
    const t = this.drawTimes;
    return t.length > 1 ? ((t.length - 1) * 1000) / (t[t.length - 1] - t[0]) : 0;
  }

  /**
   * The test API, window.atgsPlayer (browser tests and bench/web.py use it):
   * - whenFirstFrame(): Promise, resolved once the first frame is drawn (rejected on an error)
   * - seek(i): Promise, resolved once exported frame i is drawn (waits for its chunk)
   * - setCamera(i): show training camera i; returns a Promise resolved once it is drawn
   * - play(), pause()
   * - state(): {frame, frames, playing, loop, speed, buffering, camera (training index or null), loadedBytes
   *   (chunk bytes fetched so far, refetches included), totalBytes (the chunk files' total),
   *   framesDrawn, error (the error line as shown: null once a failed file loaded), note, firstFrameMs (ms from navigation start to the first drawn frame),
   *   drawFps (draws per second over the last 2 s), contextLost, contextRestores, and the
   *   stream's memory (stream.js Stream.memory: heldBytes, heldChunks, peakHeldBytes,
   *   peakHeldChunks, budgetBytes, maxChunks, decodedChunks, fetchedBytes, downloads, windowFull;
   *   a model stream's lastDecode: model_stream.js)}
   * - readPixels(): {width, height, encoding: 'base64', data}: the last drawn image (RGBA bytes,
   *   top row first), drawn again and read back at once
   * - gaussians(i): Promise of exported frame i's Gaussians as the page decoded them (a model
   *   stream only; model_stream.js ModelStream.gaussians)
   * - drawnGaussians(): the Gaussians of the last drawn frame as the renderer's textures hold them
   *   (renderer.js readGaussians: what the renderer received, read back from the GPU)
   */
  api() {
    return {
      whenFirstFrame: () => (this.framesDrawn > 0 ? Promise.resolve() : this._whenDrawn(() => true)),
      seek: (i) => {
        const n = this.manifest?.frames.length;
        if (n !== undefined && !(Number.isInteger(i) && i >= 0 && i < n)) {
          return Promise.reject(new RangeError(`seek(${i}): the stream has ${n} frames`));
        }
        const done = this._whenDrawn((f) => f === i);
        if (this.manifest) this._requestFrame(i);
        else this.options.frame = i;
        return done;
      },
      setCamera: (i) => {
        this.setCamera(i);
        return this._whenDrawn(() => true);
      },
      play: () => this.play(),
      pause: () => this.pause(),
      state: () => ({
        frame: this.frame,
        frames: this.manifest ? this.manifest.frames.length : 0,
        playing: this.playing,
        loop: this.el.loop.checked, speed: Number(this.el.speed.value),
        buffering: this.buffering,
        camera: this.view ? this.view.trainingIndex : null,
        ...(this.stream ? this.stream.memory() : {}),
        loadedBytes: this.stream ? this.stream.fetchedBytes : 0,
        totalBytes: this.stream ? this.stream.totalBytes : 0,
        framesDrawn: this.framesDrawn,
        error: this.error,
        note: this.note,
        contextLost: this.contextLost,
        contextRestores: this.contextRestores,
        firstFrameMs: this.firstFrameMs,
        drawFps: this._drawFps(),
      }),
      gaussians: (i) => {
        if (!this.stream?.gaussians) return Promise.reject(new Error('gaussians(i): the stream is not a model stream'));
        return this.stream.gaussians(i);
      },
      drawnGaussians: () => {
        if (!this.last) throw new Error('nothing drawn yet');
        return this.renderer.readGaussians(this.last.chunk.G);
      },
      readPixels: () => {
        if (!this.last) throw new Error('nothing drawn yet');
        const { chunk, local, view } = this.last;
        this.renderer.draw(chunk, local, view);
        return this.renderer.readPixels();
      },
    };
  }
}
