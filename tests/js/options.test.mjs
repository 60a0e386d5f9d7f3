// The page's URL parameters of streaming (player.js pageOptions): budget and ahead.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { pageOptions } from '../../atgs/web/player/player.js';

const parse = (query) => pageOptions(new URLSearchParams(query));

test('budget is megabytes, ahead a number of chunks; neither given: the stream decides', () => {
  const o = parse('budget=2.5&ahead=3');
  assert.equal(o.budgetBytes, 2.5e6);
  assert.equal(o.maxChunks, 3);
  assert.equal(o.error, null);
  const d = parse('');
  assert.equal(d.budgetBytes, null);
  assert.equal(d.maxChunks, null);
});

test('a budget that is not a positive number, or ahead=0, is one line on the page', () => {
  assert.equal(parse('budget=0').error, 'URL parameter budget=0 is not a positive number');
  assert.equal(parse('budget=lots').error, 'URL parameter budget=lots is not a positive number');
  assert.equal(parse('ahead=0').error, 'URL parameter ahead=0: the player holds at least the chunk it plays (ahead=1)');
  assert.equal(parse('ahead=1.5').error, 'URL parameter ahead=1.5 is not a non-negative integer');
});
