// Which stream a folder holds (manifest.json's "kind"): the Gaussian chunks of stream.js, or the
// model itself (model_stream.js, kind "model"). Both offer the player one interface (locate,
// setPlayhead, decodedNow, chunk, failed, url, units, loadedBytes, totalBytes).

import { Stream, FORMAT, VERSION } from './stream.js';
import { ModelStream } from './model_stream.js';

/** Checks a model manifest's fields the player relies on; throws one line naming the first problem. */
export function checkModelManifest(m, where) {
  const fail = (what) => { throw new Error(`${where}: ${what}`); };
  if (m.format !== FORMAT) fail(`format is ${JSON.stringify(m.format)}, not "${FORMAT}"`);
  if (m.version !== VERSION) fail(`version ${m.version} is not supported (this player reads version ${VERSION})`);
  if (!Array.isArray(m.frames) || m.frames.length === 0) fail('"frames" is empty');
  if (!(m.fps > 0)) fail(`fps ${m.fps} is not a positive number`);
  const model = m.model;
  if (!model || !Array.isArray(model.parts) || !Array.isArray(model.frames)) fail('"model" lists no parts or frames');
  if (model.frames.length !== m.frames.length) fail(`"model" describes ${model.frames.length} frames, the stream has ${m.frames.length}`);
  model.parts.forEach((p, i) => {
    if (typeof p.file !== 'string' || !p.file) fail(`part ${i} has no file name`);
    if (!Number.isInteger(p.bytes) || p.bytes <= 0) fail(`${p.file} has no byte size`);
  });
  if (!Array.isArray(m.cameras)) fail('"cameras" is missing');
  for (const key of ['near', 'dilation', 'alpha_min', 'alpha_max', 'extent']) {
    if (typeof m.render?.[key] !== 'number') fail(`render.${key} is missing`);
  }
}

/**
 * Open the stream folder `base`: read its manifest once and start the stream of its kind.
 * @param {string} base folder URL ("stream/")
 * @param {WebGL2RenderingContext} gl the renderer's context (a model stream decodes on it)
 * @param {object} options the Stream options (fetch, onProgress, onError, ...)
 * @returns {Promise<Stream|ModelStream>} opened: its manifest is read
 */
export async function openStream(base, gl, options = {}) {
  const fetcher = options.fetch ?? ((url) => globalThis.fetch(url));
  const chunked = new Stream(base, options);
  const where = chunked.url('manifest.json');
  let text = null;
  try {
    const response = await fetcher(where);
    if (response.ok) text = await response.text();
  } catch {
    text = null;  // the Stream below fetches it again and reports the failure in its words
  }
  let manifest = null;
  try {
    manifest = text === null ? null : JSON.parse(text);
  } catch {
    manifest = null;
  }
  if (manifest?.kind === 'model') {
    try {
      checkModelManifest(manifest, where);
    } catch (e) {
      options.onError?.(e, undefined);
      throw e;
    }
    return new ModelStream(base, manifest, gl, options);
  }
  // a Gaussian stream (or a manifest the Stream reports on): it reads the bytes read here
  const once = text;
  const stream = new Stream(base, {
    ...options,
    fetch: (url) => (url === where && once !== null ? Promise.resolve(new Response(once)) : fetcher(url)),
  });
  await stream.open();
  return stream;
}
