// controls.js against hand-computed gestures, wheel events and key presses.
import assert from 'node:assert/strict';
import { readFileSync } from 'node:fs';
import { test } from 'node:test';

import { ViewCamera, cameraCenter, project } from '../../atgs/web/player/camera.js';
import {
  Gestures, KEYS, KEY_ORBIT_RADIANS, KEY_ZOOM_FACTOR, WHEEL_ZOOM_MAX_STEP, applyMotion, helpRows, keyEntry,
  twoFingerMotion, wheelZoomFactor,
} from '../../atgs/web/player/controls.js';

const near = (a, b, tol = 1e-12) => assert.ok(Math.abs(a - b) <= tol, `${a} != ${b}`);
const sameMotion = (got, want) => {
  assert.equal(got.kind, want.kind);
  for (const k of ['dx', 'dy', 'scale']) if (k in want) near(got[k], want[k]);
};

test('two fingers: the midpoint pans, the ratio of their distances scales', () => {
  // spread symmetrically from 10 to 20 px apart: scale 2, the midpoint stays
  sameMotion({ kind: 'pinch', ...twoFingerMotion({ x: 0, y: 0 }, { x: 10, y: 0 }, { x: -5, y: 0 }, { x: 15, y: 0 }) },
    { kind: 'pinch', dx: 0, dy: 0, scale: 2 });
  // both moved by (3, 4): a pan of (3, 4), no scale
  sameMotion({ kind: 'pinch', ...twoFingerMotion({ x: 0, y: 0 }, { x: 10, y: 0 }, { x: 3, y: 4 }, { x: 13, y: 4 }) },
    { kind: 'pinch', dx: 3, dy: 4, scale: 1 });
  // turned 90 degrees about their midpoint (5, 0): neither pan nor scale
  sameMotion({ kind: 'pinch', ...twoFingerMotion({ x: 0, y: 0 }, { x: 10, y: 0 }, { x: 5, y: -5 }, { x: 5, y: 5 }) },
    { kind: 'pinch', dx: 0, dy: 0, scale: 1 });
  // one finger still at (0, 0), the other from (30, 40) (50 away) to (60, 80) (100 away):
  // the midpoint moves by half the finger's motion, the scale is 100 / 50
  sameMotion({ kind: 'pinch', ...twoFingerMotion({ x: 0, y: 0 }, { x: 30, y: 40 }, { x: 0, y: 0 }, { x: 60, y: 80 }) },
    { kind: 'pinch', dx: 15, dy: 20, scale: 2 });
  // fingers on top of each other: no scale from a ratio of two tiny distances
  near(twoFingerMotion({ x: 0, y: 0 }, { x: 1, y: 0 }, { x: 0, y: 0 }, { x: 3, y: 0 }).scale, 1);
});

test('one pointer orbits, or pans when it is a right, middle or shift drag', () => {
  const g = new Gestures();
  g.down(1, 100, 50);
  sameMotion(g.move(1, 107, 46), { kind: 'orbit', dx: 7, dy: -4 });
  sameMotion(g.move(1, 107, 50), { kind: 'orbit', dx: 0, dy: 4 });
  g.up(1);
  assert.equal(g.move(1, 200, 200), null, 'a lifted pointer moves nothing');
  g.down(2, 10, 10, true);
  sameMotion(g.move(2, 5, 30), { kind: 'pan', dx: -5, dy: 20 });
});

// A pinch's totals since the pair formed, before and after the event.
const pinch = (before, after) => ({ kind: 'pinch', before, after });
const samePinch = (got, want) => {
  assert.equal(got.kind, 'pinch');
  for (const when of ['before', 'after']) for (const k of ['dx', 'dy', 'scale']) near(got[when][k], want[when][k]);
};
const still = { dx: 0, dy: 0, scale: 1 };

test('a second finger landing or lifting makes no jump', () => {
  const g = new Gestures();
  g.down('a', 100, 100);
  sameMotion(g.move('a', 110, 100), { kind: 'orbit', dx: 10, dy: 0 });
  // b lands 200 px to the right: nothing moves (the old player orbited by the 190 px between them
  // at a's next move)
  g.down('b', 310, 100);
  // a moves 10 px left: the midpoint (210, 100) -> (205, 100), the span 200 -> 210
  samePinch(g.move('a', 100, 100), pinch(still, { dx: -5, dy: 0, scale: 210 / 200 }));
  // b moves down 20: the midpoint moves 10 down more, the span is hypot(210, 20), both since b landed
  samePinch(g.move('b', 310, 120), pinch({ dx: -5, dy: 0, scale: 210 / 200 }, { dx: -5, dy: 10, scale: Math.hypot(210, 20) / 200 }));
  // b lifts; a goes on from where it is, not from where b was
  g.up('b');
  sameMotion(g.move('a', 103, 98), { kind: 'orbit', dx: 3, dy: -2 });
  // the other way round: a lifts, b (landed again) goes on alone
  g.down('b', 300, 300);
  g.up('a');
  sameMotion(g.move('b', 301, 300), { kind: 'orbit', dx: 1, dy: 0 });
});

test('a third finger is ignored, and takes over without a jump when one of the two lifts', () => {
  const g = new Gestures();
  g.down(1, 0, 0);
  g.down(2, 100, 0);
  g.down(3, 50, 80);
  assert.equal(g.move(3, 60, 90), null);
  g.up(1);
  // fingers 2 (100, 0) and 3 (60, 90) are the pair now: 3 moves to (60, 100)
  samePinch(g.move(3, 60, 100), pinch(still, { dx: 0, dy: 5, scale: Math.hypot(40, 100) / Math.hypot(40, 90) }));
});

// A ViewCamera driven by applyMotion, on a canvas of the camera's size.
function viewDrivenBy(events) {
  const cam = { width: 320, height: 240, fx: 300, fy: 300, cx: 160, cy: 120,
    w2c: [0, 1, 0, 0, 0, 0, -1, 0, -1, 0, 0, 4, 0, 0, 0, 1] };  // at (4, 0, 0) looking at the origin
  const view = new ViewCamera({ center: [0, 0, 0], radius: 4, up: [0, 0, 1] });
  view.setTraining(cam, 0);
  const commands = { orbit: (y, p) => view.orbit(y, p), pan: (dx, dy) => view.pan(dx, dy, cam), zoom: (f) => view.zoom(f) };
  const g = new Gestures();
  for (const [what, id, x, y] of events) {
    if (what === 'down') g.down(id, x, y);
    else if (what === 'up') g.up(id);
    else applyMotion(g.move(id, x, y), commands);
  }
  return { view, cam };
}

test('a two-finger gesture\'s view depends on where the fingers go, not on the order of their events', () => {
  // a to the left and up, b to the right and up: a pan of (0, -30) and a spread from 100 to 160 px
  const start = [['down', 'a', 110, 120], ['down', 'b', 210, 120]];
  const aFirst = viewDrivenBy([...start, ['move', 'a', 80, 90], ['move', 'b', 240, 90]]);
  const bFirst = viewDrivenBy([...start, ['move', 'b', 240, 90], ['move', 'a', 80, 90]]);
  const steps = [...start];
  for (let k = 1; k <= 5; k++) steps.push(['move', 'b', 210 + 6 * k, 120 - 6 * k], ['move', 'a', 110 - 6 * k, 120 - 6 * k]);
  const stepped = viewDrivenBy(steps);
  for (const other of [bFirst, stepped]) aFirst.view.w2c.forEach((v, i) => near(v, other.view.w2c[i], 1e-12));
  // and it is the analytic one: 4 / 1.6 from the centre, the centre 30 px up from the principal point
  const { view, cam } = aFirst;
  near(Math.hypot(...cameraCenter(view.w2c).map((v, i) => v - view.center[i])), 4 / 1.6, 1e-12);
  const c = project(view.w2c, cam, [0, 0, 0]);
  near(c[0], 160, 1e-9);
  near(c[1], 90, 1e-9);
});

test('the reverse of a two-finger pan, and of a pinch about a still midpoint, restores the view', () => {
  const home = viewDrivenBy([]).view.w2c;
  // one finger at a time (the scale changes between their events), 40 px right and back
  const pan = viewDrivenBy([['down', 'a', 100, 100], ['down', 'b', 200, 100], ['move', 'a', 140, 100], ['move', 'b', 240, 100],
    ['up', 'a'], ['up', 'b'], ['down', 'b', 240, 100], ['down', 'a', 140, 100], ['move', 'b', 200, 100], ['move', 'a', 100, 100]]);
  home.forEach((v, i) => near(v, pan.view.w2c[i], 1e-12));
  // spread from 100 to 200 px about (150, 100), and back
  const pinched = viewDrivenBy([['down', 'a', 100, 100], ['down', 'b', 200, 100], ['move', 'a', 50, 100], ['move', 'b', 250, 100],
    ['move', 'a', 100, 100], ['move', 'b', 200, 100]]);
  home.forEach((v, i) => near(v, pinched.view.w2c[i], 1e-12));
});

test('wheel: pixels, lines and pages alike, ctrl+wheel (a trackpad pinch) amplified, each event bounded', () => {
  near(wheelZoomFactor({ deltaY: 100, deltaMode: 0 }), Math.exp(0.1));          // a notch in Chrome: 10 % away
  near(wheelZoomFactor({ deltaY: -100, deltaMode: 0 }), Math.exp(-0.1));        // and back
  near(wheelZoomFactor({ deltaY: 3, deltaMode: 1 }), Math.exp(3 * 16 * 0.001)); // Firefox: 3 lines of 16 px
  near(wheelZoomFactor({ deltaY: 0.1, deltaMode: 2 }, 400), Math.exp(0.1 * 400 * 0.001));
  near(wheelZoomFactor({ deltaY: -4, deltaMode: 0, ctrlKey: true }), Math.exp(-0.04));
  near(wheelZoomFactor({ deltaY: 1e5, deltaMode: 0 }), Math.exp(WHEEL_ZOOM_MAX_STEP));
  near(wheelZoomFactor({ deltaY: -1e5, deltaMode: 0 }), Math.exp(-WHEEL_ZOOM_MAX_STEP));
  near(wheelZoomFactor({ deltaY: 0, deltaMode: 0 }), 1);
});

// Runs a key press and returns the commands it called.
function press(key, mods = {}) {
  const calls = [];
  const commands = new Proxy({}, { get: (_, name) => (...args) => calls.push([name, ...args]) });
  const entry = keyEntry({ key, ...mods });
  if (entry) entry.run(commands, 30, key.length === 1 ? key.toLowerCase() : key);
  return calls;
}

test('keys: a video player\'s, and the view\'s', () => {
  assert.deepEqual(press(' '), [['togglePlay']]);
  assert.deepEqual(press('K', { shiftKey: true }), [['togglePlay']]);
  assert.deepEqual(press(','), [['step', -1]]);
  assert.deepEqual(press('.'), [['step', 1]]);
  assert.deepEqual(press('Home'), [['seekFraction', 0]]);
  assert.deepEqual(press('End'), [['seekFraction', 1]]);
  assert.deepEqual(press('5'), [['seekFraction', 0.5]]);
  assert.deepEqual(press('l'), [['toggleLoop']]);
  assert.deepEqual(press('['), [['changeSpeed', -1]]);
  assert.deepEqual(press('>', { shiftKey: true }), [['changeSpeed', 1]]);
  assert.deepEqual(press('ArrowRight'), [['orbit', KEY_ORBIT_RADIANS, 0]]);
  assert.deepEqual(press('ArrowUp'), [['orbit', 0, -KEY_ORBIT_RADIANS]]);
  assert.deepEqual(press('ArrowLeft', { shiftKey: true }), [['pan', -30, 0]]);
  assert.deepEqual(press('ArrowDown', { shiftKey: true }), [['pan', 0, 30]]);
  assert.deepEqual(press('+', { shiftKey: true }), [['zoom', 1 / KEY_ZOOM_FACTOR]]);
  assert.deepEqual(press('-'), [['zoom', KEY_ZOOM_FACTOR]]);
  assert.deepEqual(press('r'), [['resetView']]);
  assert.deepEqual(press('c'), [['changeCamera', 1]]);
  assert.deepEqual(press('?', { shiftKey: true }), [['toggleHelp']]);
  // the browser's own shortcuts, and keys without a meaning, pass through
  assert.deepEqual(press('r', { ctrlKey: true }), []);
  assert.deepEqual(press('l', { metaKey: true }), []);
  assert.deepEqual(press('ArrowLeft', { altKey: true }), []);
  assert.deepEqual(press('x'), []);
  assert.deepEqual(press('Tab'), []);
});

test('docs/web.md\'s controls table lists every row of the page\'s help', () => {
  const doc = readFileSync(new URL('../../docs/web.md', import.meta.url), 'utf8');
  const rows = new Set(doc.split('\n').filter((l) => l.startsWith('| ')).map((l) => l.split('|').slice(1, 3).map((c) => c.trim()).join(' | ')));
  for (const [label, does] of helpRows()) {
    const md = label.replace(/\|/g, '\\|');
    assert.ok(rows.has(`\`${md}\` | ${does}`) || rows.has(`${md} | ${does}`), `docs/web.md lacks the row "| ${label} | ${does} |"`);
  }
  assert.equal(helpRows().length, KEYS.length + 3);
});
