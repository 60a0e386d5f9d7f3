// The page's input: pointer (mouse, pen, touch), wheel and keyboard, turned into view moves and
// player commands. The gesture maths and the key table are pure (tests/js/controls.test.mjs);
// attachControls wires them to the DOM. docs/web.md's controls table lists the same keys.

export const ORBIT_RADIANS_PER_PIXEL = 0.005;  // CSS pixels of drag
export const KEY_ORBIT_RADIANS = (5 * Math.PI) / 180;
export const KEY_PAN_FRACTION = 0.05;          // of the canvas height, per key press
export const KEY_ZOOM_FACTOR = 1.25;           // distance multiplier per key press (- key; + divides)
export const WHEEL_ZOOM_PER_PIXEL = 0.001;     // a mouse notch (100 px in Chrome): 10 %
export const WHEEL_ZOOM_MAX_STEP = 0.5;        // at most e^0.5 per event: a page-sized delta does not jump
const WHEEL_LINE_PIXELS = 16;                  // deltaMode 1 (Firefox's mouse wheel)
const PINCH_WHEEL_GAIN = 10;                   // a trackpad pinch: ctrl+wheel with small deltas
const MIN_PINCH_SPAN = 8;                      // CSS px: fingers closer than this give no scale

/** Midpoint and distance of two points {x, y}. */
export function span(a, b) {
  return { x: 0.5 * (a.x + b.x), y: 0.5 * (a.y + b.y), d: Math.hypot(b.x - a.x, b.y - a.y) };
}

/**
 * Two fingers moving from (a0, b0) to (a1, b1): the pan is the motion of their midpoint; the
 * scale the ratio of their distances (> 1: they spread, the picture grows). Fingers that (nearly)
 * touch give scale 1: a ratio of two tiny distances is noise.
 * @returns {{dx: number, dy: number, scale: number}}
 */
export function twoFingerMotion(a0, b0, a1, b1) {
  const s0 = span(a0, b0), s1 = span(a1, b1);
  const scale = s0.d >= MIN_PINCH_SPAN && s1.d >= MIN_PINCH_SPAN ? s1.d / s0.d : 1;
  return { dx: s1.x - s0.x, dy: s1.y - s0.y, scale };
}

/**
 * The pointers on the canvas and the motion each event makes. Every pointer keeps its own last
 * position, so a finger landing or lifting moves nothing (the next motion starts from where each
 * finger is): one pointer orbits (or pans: a right, middle or shift drag), two pinch and pan, a
 * third is ignored. Pure: positions in, motions out.
 *
 * Two fingers report their whole motion since the pair formed (`before` and `after` this event,
 * as twoFingerMotion), not a step: a browser moves one finger per event, and steps of pan and
 * zoom do not commute, so summed steps would leave the view depending on the order the fingers
 * were reported in. applyMotion turns the pair into one view: zoomed by the total scale, then
 * panned by the total midpoint motion.
 */
export class Gestures {
  constructor() {
    this.pointers = new Map();  // id -> {x, y, pan}, in landing order
    this.pair = null;           // where the two fingers were when they became a pair
  }

  /** A pointer lands at (x, y); `pan`: it pans instead of orbiting when alone. */
  down(id, x, y, pan = false) {
    this.pointers.set(id, { x, y, pan });
    this._newPair();
  }

  /** A pointer lifts (or is cancelled). */
  up(id) {
    this.pointers.delete(id);
    this._newPair();
  }

  _newPair() {
    const [a, b] = this.pointers.values();
    this.pair = b ? { a: { ...a }, b: { ...b } } : null;
  }

  /**
   * Pointer `id` moves to (x, y).
   * @returns {null | {kind: 'orbit' | 'pan', dx: number, dy: number}
   *   | {kind: 'pinch', before: Motion, after: Motion}} the motion, in CSS pixels (Motion: what
   *   twoFingerMotion returns, from where the pair formed)
   */
  move(id, x, y) {
    const p = this.pointers.get(id);
    if (!p) return null;
    const [a, b] = this.pointers.values();
    if (!b) {
      const motion = { kind: p.pan ? 'pan' : 'orbit', dx: x - p.x, dy: y - p.y };
      p.x = x;
      p.y = y;
      return motion;
    }
    const before = twoFingerMotion(this.pair.a, this.pair.b, a, b);
    p.x = x;
    p.y = y;
    if (p !== a && p !== b) return null;  // a third finger: followed (it may take over), ignored
    return { kind: 'pinch', before, after: twoFingerMotion(this.pair.a, this.pair.b, a, b) };
  }
}

/**
 * Applies a motion of Gestures.move to the view: orbit(yaw, pitch) radians, pan(dx, dy) canvas
 * pixels, zoom(factor) distance multiplier. A pinch takes back the pair's pan so far, changes
 * the zoom to its new total, and pans by the new total: the view is then the one at the pair's
 * start, zoomed by 1 / scale and panned by the midpoint's motion, whatever order the fingers'
 * events came in (pans at one depth add up; zooms about the centre multiply).
 * @param {ReturnType<Gestures['move']>} m
 * @param {{orbit: Function, pan: Function, zoom: Function}} view
 * @param {number} canvasPixels canvas pixels per CSS pixel
 */
export function applyMotion(m, view, canvasPixels = 1) {
  if (!m) return;
  const k = canvasPixels;
  const pan = (dx, dy) => { if (dx !== 0 || dy !== 0) view.pan(dx * k, dy * k); };
  if (m.kind === 'orbit') {
    if (m.dx !== 0 || m.dy !== 0) view.orbit(m.dx * ORBIT_RADIANS_PER_PIXEL, m.dy * ORBIT_RADIANS_PER_PIXEL);
  } else if (m.kind === 'pan') {
    pan(m.dx, m.dy);
  } else {
    const { before, after } = m;
    pan(-before.dx, -before.dy);
    if (before.scale !== after.scale) view.zoom(before.scale / after.scale);  // fingers spread: come closer
    pan(after.dx, after.dy);
  }
}

/**
 * The distance multiplier of one wheel event (> 1: away from the centre). Lines (deltaMode 1)
 * and pages (2) count as pixels; a ctrl+wheel (a trackpad's pinch) is amplified; one event moves
 * at most e^WHEEL_ZOOM_MAX_STEP.
 * @param {{deltaY: number, deltaMode?: number, ctrlKey?: boolean}} e
 * @param {number} pagePixels what a page of scrolling is (the canvas height)
 */
export function wheelZoomFactor(e, pagePixels = 800) {
  const unit = e.deltaMode === 1 ? WHEEL_LINE_PIXELS : e.deltaMode === 2 ? pagePixels : 1;
  const step = e.deltaY * unit * WHEEL_ZOOM_PER_PIXEL * (e.ctrlKey ? PINCH_WHEEL_GAIN : 1);
  return Math.exp(Math.max(-WHEEL_ZOOM_MAX_STEP, Math.min(WHEEL_ZOOM_MAX_STEP, step)));
}

/**
 * The keyboard, in the order of the help: `keys` as KeyboardEvent.key values (' ' is Space),
 * `shift` true when the entry needs Shift (arrows only: other keys are matched by the character
 * Shift makes), `label` as docs/web.md's table and the page's help show it, `run(commands, pan)`
 * the command (`pan`: canvas pixels one pan key moves).
 */
export const KEYS = [
  { keys: [' ', 'k'], label: 'Space, K', does: 'play / pause', run: (c) => c.togglePlay() },
  { keys: [','], label: ',', does: 'previous frame (pauses)', run: (c) => c.step(-1) },
  { keys: ['.'], label: '.', does: 'next frame (pauses)', run: (c) => c.step(1) },
  { keys: ['Home'], label: 'Home', does: 'first frame', run: (c) => c.seekFraction(0) },
  { keys: ['End'], label: 'End', does: 'last frame', run: (c) => c.seekFraction(1) },
  { keys: ['0', '1', '2', '3', '4', '5', '6', '7', '8', '9'], label: '0-9', does: 'jump to 0 %-90 % of the video',
    run: (c, _, key) => c.seekFraction(Number(key) / 10) },
  { keys: ['l'], label: 'L', does: 'loop on / off', run: (c) => c.toggleLoop() },
  { keys: ['[', '<'], label: '[ or <', does: 'slower', run: (c) => c.changeSpeed(-1) },
  { keys: [']', '>'], label: '] or >', does: 'faster', run: (c) => c.changeSpeed(1) },
  { keys: ['ArrowLeft', 'ArrowRight', 'ArrowUp', 'ArrowDown'], label: 'arrows', does: 'orbit (as dragging that way)',
    run: (c, _, key) => c.orbit(...arrow(key, KEY_ORBIT_RADIANS)) },
  { keys: ['ArrowLeft', 'ArrowRight', 'ArrowUp', 'ArrowDown'], shift: true, label: 'Shift + arrows', does: 'pan',
    run: (c, pan, key) => c.pan(...arrow(key, pan)) },
  { keys: ['+', '='], label: '+', does: 'zoom in', run: (c) => c.zoom(1 / KEY_ZOOM_FACTOR) },
  { keys: ['-', '_'], label: '-', does: 'zoom out', run: (c) => c.zoom(KEY_ZOOM_FACTOR) },
  { keys: ['r'], label: 'R', does: 'reset the view to the camera chosen in the menu', run: (c) => c.resetView() },
  { keys: ['c'], label: 'C', does: 'next training camera', run: (c) => c.changeCamera(1) },
  { keys: ['?'], label: '?', does: 'show / hide this help', run: (c) => c.toggleHelp() },
];

// An arrow key as a drag of `amount` that way: [dx, dy].
function arrow(key, amount) {
  return { ArrowLeft: [-amount, 0], ArrowRight: [amount, 0], ArrowUp: [0, -amount], ArrowDown: [0, amount] }[key];
}

/**
 * The KEYS entry a key press runs, or null (a press with Ctrl, Alt or Meta belongs to the browser).
 * @param {{key: string, shiftKey?: boolean, ctrlKey?: boolean, altKey?: boolean, metaKey?: boolean}} e
 */
export function keyEntry(e) {
  if (e.ctrlKey || e.altKey || e.metaKey) return null;
  const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
  const arrowKey = key.startsWith('Arrow');
  return KEYS.find((k) => k.keys.includes(key) && (!arrowKey || Boolean(k.shift) === Boolean(e.shiftKey))) ?? null;
}

/**
 * Wires the canvas's pointer and wheel input, and the page's keys, to `commands`:
 * orbit(yaw, pitch) radians, pan(dx, dy) canvas pixels, zoom(factor) distance multiplier,
 * togglePlay(), step(frames), seekFraction(f), toggleLoop(), changeSpeed(+-1), resetView(),
 * changeCamera(+-1), toggleHelp(). Keys act when the canvas or nothing has the focus: a focused
 * button, select or the scrub bar keeps its own keys.
 * @param {HTMLCanvasElement} canvas
 * @param {object} commands
 */
export function attachControls(canvas, commands) {
  const doc = canvas.ownerDocument;
  const gestures = new Gestures();
  const canvasPixels = () => canvas.width / Math.max(1, canvas.clientWidth);  // CSS px -> canvas px
  canvas.addEventListener('contextmenu', (e) => e.preventDefault());
  canvas.addEventListener('pointerdown', (e) => {
    gestures.down(e.pointerId, e.clientX, e.clientY, e.button === 1 || e.button === 2 || e.shiftKey);
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointermove', (e) => {
    applyMotion(gestures.move(e.pointerId, e.clientX, e.clientY), commands, canvasPixels());
  });
  for (const type of ['pointerup', 'pointercancel', 'lostpointercapture']) {
    canvas.addEventListener(type, (e) => gestures.up(e.pointerId));
  }
  canvas.addEventListener('wheel', (e) => {
    e.preventDefault();  // neither the page's scroll nor (ctrl+wheel) the browser's zoom
    commands.zoom(wheelZoomFactor(e, canvas.clientHeight || 800));
  }, { passive: false });
  doc.addEventListener('keydown', (e) => {
    if (e.target !== canvas && e.target !== doc.body && e.target !== doc.documentElement) return;
    const entry = keyEntry(e);
    if (!entry) return;
    e.preventDefault();
    const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    entry.run(commands, KEY_PAN_FRACTION * canvas.height, key);
  });
}

/** The help's rows, [label, what it does]: the pointer's first, then KEYS. */
export function helpRows() {
  return [
    ['drag, one finger', 'orbit'],
    ['right-drag, shift-drag, two fingers', 'pan'],
    ['wheel, pinch', 'zoom'],
    ...KEYS.map((k) => [k.label, k.does]),
  ];
}

/** Fills a <table> with helpRows(). */
export function fillHelp(table) {
  const doc = table.ownerDocument;
  for (const [label, does] of helpRows()) {
    const row = table.insertRow();
    const th = doc.createElement('th');
    th.textContent = label;
    row.append(th);
    row.insertCell().textContent = does;
  }
}
