// Which stream a folder holds (manifest.json's "kind"): the Gaussian chunks of stream.js, or the
// model itself (model_stream.js, kind "model"). Both offer the player one interface (locate,
// setPlayhead(unit, asked), setWrap, decodedNow, chunk, failure, url, fetchFile, units, memory,
// fetchedBytes, totalBytes, budgetBytes, contextRestored), fetch through fetcher.js and hold their
// files in a window.js FetchWindow within the page's byte budget, fetching a failed file again by
// retry.js's rule.

import { StreamFolder } from './fetcher.js';
import { ModelStream } from './model_stream.js';
import { Stream, checkCommonManifest, readManifest } from './stream.js';

/** Checks a model manifest's fields the player relies on; throws one line naming the first problem. */
export function checkModelManifest(m, where) {
  checkCommonManifest(m, where);
  const fail = (what) => { throw new Error(`${where}: ${what}`); };
  const model = m.model;
  if (!model || !Array.isArray(model.parts) || !Array.isArray(model.frames)) fail('"model" lists no parts or frames');
  if (model.frames.length !== m.frames.length) fail(`"model" describes ${model.frames.length} frames, the stream has ${m.frames.length}`);
  model.parts.forEach((p, i) => {
    if (typeof p.file !== 'string' || !p.file) fail(`part ${i} has no file name`);
    if (!Number.isInteger(p.bytes) || p.bytes <= 0) fail(`${p.file} has no byte size`);
    if (!Number.isInteger(p.values) || p.values < 0) fail(`${p.file} has no value count (export it again with this version)`);
  });
}

/**
 * Open the stream folder `base`: read its manifest once and start the stream of its kind.
 * @param {string} base folder URL ("stream/")
 * @param {WebGL2RenderingContext} gl the renderer's context (a model stream decodes on it)
 * @param {object} options the Stream options (fetch, budgetBytes, maxChunks, onProgress, onError, ...)
 * @returns {Promise<Stream|ModelStream>} opened: its manifest is read
 */
export async function openStream(base, gl, options = {}) {
  const folder = new StreamFolder(base, options);
  const where = folder.url('manifest.json');
  let manifest;
  try {
    manifest = await readManifest(folder);
    if (manifest?.kind === 'model') checkModelManifest(manifest, where);
  } catch (e) {
    options.onError?.(e, undefined);
    throw e;
  }
  if (manifest.kind === 'model') return new ModelStream(base, manifest, gl, options);
  const stream = new Stream(base, options);
  await stream.open(manifest);  // checks it as a chunk stream's, reports a failure through onError
  return stream;
}
