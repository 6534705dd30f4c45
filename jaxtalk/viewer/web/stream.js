// The page `jaxtalk export-model` writes: the exported stream (manifest.json and its ONNX graphs) runs here, in the
// browser, on onnxruntime-web's WebAssembly backend, fed by the microphone (or a file), and drives the face
// (face.glb). No server computes anything: the folder's files are all it loads.
//
// The protocol is the reference host's (host.py in this folder): audio in groups of `chunk_tokens` tokens through
// frontend.onnx, each chunk of tokens through step.onnx with its state carried and fresh standard-normal noise
// for its new frames, the head parameters through morph.onnx to the face's morph weights and joint rotations
// (quaternion signs kept continuous). Each chunk's first frame is drawn as soon as it is computed and the
// others a frame period apart (an older chunk's frames not drawn by then are skipped).
//
// Query: ?source=mic (start the microphone at once), ?seed=N (the noise generator's seed, default 0),
// ?record=1 (keep the noise fed to the model, for a test to replay). `window.jaxtalkStream` exposes the state,
// per-chunk compute times and latencies, the drawn frames and the audio captured (what the browser test reads).
import * as ort from "./vendor/onnxruntime-web/dist/ort.wasm.min.mjs";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { stage } from "./stage.js";
import { audioInput } from "./sources.js";

const KEEP_FRAMES = 3000; // drawn frames kept for inspection (two minutes at 25 fps)
const query = new URLSearchParams(location.search);
const statusLine = document.getElementById("status");
const buttons = { mic: document.getElementById("mic"), file: document.getElementById("file"), stop: document.getElementById("stop") };

const page = {
  state: "loading", errors: [], manifest: null, chunks: [], drawn: [], noise: [], sentSamples: 0, frameRms: [],
  audio: null, startedAt: null, firstDrawnAt: null, backend: null,
  audioBase64() {
    const bytes = new Uint8Array(this.audio.buffer, 0, 4 * Math.min(this.sentSamples, this.audio.length));
    let text = "";
    for (let i = 0; i < bytes.length; i += 0x8000) text += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
    return btoa(text);
  },
};
window.jaxtalkStream = page;
const fail = (message) => { page.errors.push(String(message?.stack ?? message)); page.state = "error"; statusLine.textContent = `error: ${message}`; };

// ------------------------------------------------------------------ the model
const manifest = await (await fetch("manifest.json")).json();
if (manifest.format !== "jaxtalk-onnx-stream" || manifest.version !== 1) throw new Error("manifest.json is not a jaxtalk ONNX stream (version 1)");
page.manifest = { model: manifest.model, run: manifest.run, fps: manifest.fps, chunk_frames: manifest.chunk_frames,
                  sample_steps: manifest.sample_steps };
const RATE = manifest.sample_rate;
page.audio = new Float32Array(60 * RATE);
ort.env.logLevel = "error"; // not its notes on the graph's unused constants
ort.env.wasm.wasmPaths = new URL("vendor/onnxruntime-web/dist/", location.href).href;
// Threads need a cross-origin-isolated page (SharedArrayBuffer); a plain static server gives one thread.
ort.env.wasm.numThreads = self.crossOriginIsolated ? Math.min(4, navigator.hardwareConcurrency || 1) : 1;
page.backend = `wasm, ${ort.env.wasm.numThreads} thread(s)`;
const open = (entry) => (entry ? ort.InferenceSession.create(entry.file, { executionProviders: ["wasm"], logSeverityLevel: 3 }) : null);
const [frontend, step, morph] = await Promise.all([open(manifest.frontend), open(manifest.step), open(manifest.morph)]);

// One call of each graph on placeholder inputs before any audio: WebAssembly compiles and allocates on a session's
// first run (hundreds of ms), which would otherwise delay the first chunk of speech. The state is not touched.
async function warmUp() {
  const placeholder = (spec) => (spec.dtype === "bool" ? new ort.Tensor("bool", new Uint8Array(size(spec.shape)), spec.shape)
    : new ort.Tensor("float32", new Float32Array(size(spec.shape)), spec.shape));
  for (const [session, entry] of [[frontend, manifest.frontend], [step, manifest.step], [morph, manifest.morph]]) {
    if (session) await session.run(Object.fromEntries(entry.inputs.map((i) => [i.name, placeholder(i)])));
  }
}

// Standard normal noise: mulberry32 uniforms through Box-Muller (the model needs only independence).
let seed = (Number(query.get("seed") ?? 0) >>> 0) || 0x9e3779b9;
function uniform() {
  seed = (seed + 0x6d2b79f5) >>> 0;
  let t = seed;
  t = Math.imul(t ^ (t >>> 15), t | 1);
  t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
  return (((t ^ (t >>> 14)) >>> 0) + 0.5) / 4294967296;
}
function normals(count) {
  const out = new Float32Array(count);
  for (let i = 0; i < count; i += 2) {
    const r = Math.sqrt(-2 * Math.log(uniform())), a = 2 * Math.PI * uniform();
    out[i] = r * Math.cos(a);
    if (i + 1 < count) out[i + 1] = r * Math.sin(a);
  }
  if (query.get("record") === "1") page.noise.push(Array.from(out));
  return out;
}

const size = (shape) => shape.reduce((a, b) => a * b, 1);
function initial(spec) {
  const n = size(spec.shape);
  if (spec.dtype === "bool") return new ort.Tensor("bool", new Uint8Array(n), spec.shape);
  const data = spec.init === "inf" ? new Float32Array(n).fill(Infinity) : spec.init === "white" ? normals(n) : new Float32Array(n);
  return new ort.Tensor("float32", data, spec.shape);
}
const scalar = (value) => new ort.Tensor("float32", new Float32Array([value]), []);

// One utterance's stream state (reference host: OnnxStream.reset).
let s;
function reset() {
  s = {
    state: Object.fromEntries(manifest.step.inputs.filter((i) => "init" in i).map((i) => [i.name, initial(i)])),
    history: manifest.frontend
      ? Object.fromEntries(manifest.frontend.inputs.filter((i) => "init" in i).map((i) => [i.name, initial(i)])) : {},
    audio: new Float32Array(0), audioStart: 0, samples: 0, groups: 0, tokens: [], frames: 0, lastQuat: {},
  };
}
reset();

async function runGroup(n) {
  const f = manifest.frontend;
  const start = n * f.hop_samples + f.offset_samples;
  const window = new Float32Array(f.window_samples);
  const lo = Math.max(start, s.audioStart), hi = Math.min(start + f.window_samples, s.audioStart + s.audio.length);
  if (hi > lo) window.set(s.audio.subarray(lo - s.audioStart, hi - s.audioStart), lo - start);
  const out = await frontend.run({ audio: new ort.Tensor("float32", window, [f.window_samples]), ...s.history });
  for (const name of Object.keys(s.history)) s.history[name] = out[`next_${name}`];
  const width = manifest.token_width, data = out.tokens.data;
  for (let k = 0; k < data.length / width; k++) s.tokens.push(data.slice(k * width, (k + 1) * width));
}

async function runChunk(tokens) {
  const m = manifest;
  const chunk = new Float32Array(m.chunk_tokens * m.token_width);
  tokens.forEach((row, k) => chunk.set(row, k * m.token_width));
  const out = await step.run({ ...s.state, chunk_tokens: new ort.Tensor("float32", chunk, [1, m.chunk_tokens, m.token_width]),
                               white_chunk: new ort.Tensor("float32", normals(m.chunk_frames * m.param_dim), [1, m.chunk_frames, m.param_dim]),
                               cfg_scale: scalar(m.cfg_scale), temperature: scalar(m.temperature) });
  for (const name of Object.keys(s.state)) s.state[name] = out[`next_${name}`];
  const params = out.params.data;
  const values = (await morph.run({ params: new ort.Tensor("float32", params, [m.chunk_frames, m.param_dim]) })).morph.data;
  const width = m.morph.channels.length;
  const rows = [];
  for (let t = 0; t < m.chunk_frames; t++) {
    const row = Array.from(values.subarray(t * width, (t + 1) * width));
    for (const at of m.morph.quaternions) {
      const last = s.lastQuat[at];
      if (last && row[at] * last[0] + row[at + 1] * last[1] + row[at + 2] * last[2] + row[at + 3] * last[3] < 0) {
        for (let c = 0; c < 4; c++) row[at + c] = -row[at + c];
      }
      s.lastQuat[at] = row.slice(at, at + 4);
    }
    rows.push({ values: row, params: Array.from(params.subarray(t * m.param_dim, (t + 1) * m.param_dim)) });
  }
  return rows;
}

// Audio of any length in; every chunk it completes computed and queued for drawing.
async function consume(samples, captured) {
  const f = manifest.frontend;
  const joined = new Float32Array(s.audio.length + samples.length);
  joined.set(s.audio);
  joined.set(samples, s.audio.length);
  s.audio = joined;
  s.samples += samples.length;
  while ((s.groups + 1) * f.hop_samples + f.lookahead_samples <= s.samples) {
    const began = performance.now();
    await runGroup(s.groups);
    s.groups += 1;
    while (s.tokens.length >= manifest.chunk_tokens) {
      const rows = await runChunk(s.tokens.splice(0, manifest.chunk_tokens));
      show(rows, s.frames, captured, performance.now() - began);
      s.frames += rows.length;
    }
  }
  const keep = s.groups * f.hop_samples + f.offset_samples; // what later groups still read
  if (keep > s.audioStart) { s.audio = s.audio.slice(keep - s.audioStart); s.audioStart = keep; }
}

// ------------------------------------------------------------------ the face
const gltf = await new GLTFLoader().loadAsync(manifest.morph.face);
const { renderer, draw } = stage(document.getElementById("scene"), gltf.scene);
let mesh = null;
gltf.scene.traverse((o) => { if (o.morphTargetDictionary && !mesh) mesh = o; });
const joints = Object.fromEntries(manifest.morph.joints.map((j) => [j, gltf.scene.getObjectByName(j)]));
const targets = [];
const quatAt = {};
manifest.morph.channels.forEach((name, c) => {
  if (name.endsWith(".qx")) quatAt[name.slice(0, -3)] = c;
  else if (!name.includes(".q")) targets.push([c, mesh.morphTargetDictionary[name]]);
});
function apply(values) {
  for (const [c, t] of targets) mesh.morphTargetInfluences[t] = values[c];
  for (const [joint, at] of Object.entries(quatAt)) joints[joint].quaternion.set(values[at], values[at + 1], values[at + 2], values[at + 3]);
}

const queue = []; // frames waiting to be drawn: {frame, values, params, due, first, captured, compute}
function show(rows, first, captured, compute) {
  const now = performance.now(), period = 1000 / manifest.fps;
  queue.length = 0; // the newest motion wins
  rows.forEach((r, i) => queue.push({ frame: first + i, ...r, due: now + i * period, first: i === 0, captured, compute }));
}

// ------------------------------------------------------------------ audio
let work = Promise.resolve(); // model calls run one after another, in the order the audio came

function onAudio(samples) {
  const captured = performance.now();
  if (page.startedAt === null) page.startedAt = captured - 1000 * samples.length / RATE; // the first sample's time
  const start = page.sentSamples;
  if (start + samples.length <= page.audio.length) page.audio.set(samples, start);
  page.sentSamples += samples.length;
  const frame = Math.round(RATE / manifest.fps); // RMS of every whole frame of audio, for a test to compare with
  for (let f = Math.floor(start / frame); (f + 1) * frame <= page.sentSamples && (f + 1) * frame <= page.audio.length; f++) {
    if (page.frameRms[f] !== undefined) continue;
    let sum = 0;
    for (let i = f * frame; i < (f + 1) * frame; i++) sum += page.audio[i] * page.audio[i];
    page.frameRms[f] = Math.sqrt(sum / frame);
  }
  work = work.then(() => consume(samples, captured)).catch(fail);
}

const input = audioInput({
  rate: RATE, block: Math.round(RATE * 0.04), worklet: "capture.js", buttons, onBlock: onAudio, fail,
  onStart: () => { page.state = "streaming"; },
  onStop: () => {
    work = work.then(reset).catch(fail); // the next utterance starts afresh
    page.state = "ready";
  },
});

// ------------------------------------------------------------------ drawing
const median = (xs) => { const v = [...xs].sort((a, b) => a - b); return v.length ? v[Math.floor(v.length / 2)] : NaN; };

renderer.setAnimationLoop(() => {
  const now = performance.now();
  let shown = null;
  const firsts = [];
  while (queue.length && queue[0].due <= now) {
    shown = queue.shift();
    if (shown.first) firsts.push(shown);
  }
  if (shown) apply(shown.values);
  draw();
  if (!shown) return;
  const drawn = performance.now();
  if (page.firstDrawnAt === null) page.firstDrawnAt = drawn;
  for (const f of firsts) {
    page.chunks.push({ frame: f.frame, latency_ms: drawn - f.captured, compute_ms: f.compute });
    if (page.chunks.length > KEEP_FRAMES) page.chunks.shift();
  }
  const q = shown.values.slice(quatAt.jaw, quatAt.jaw + 4);
  page.drawn.push({ frame: shown.frame, at: drawn, jaw: 2 * Math.atan2(Math.hypot(q[0], q[1], q[2]), Math.abs(q[3])),
                    values: shown.values, params: shown.params });
  if (page.drawn.length > KEEP_FRAMES) page.drawn.shift();
  const recent = page.chunks.slice(-50);
  statusLine.textContent = `in the browser (${page.backend}): compute ${median(recent.map((c) => c.compute_ms)).toFixed(0)} ms a chunk`
    + `, capture→drawn ${median(recent.map((c) => c.latency_ms)).toFixed(0)} ms  frame ${shown.frame}`;
});

if (!manifest.frontend) {
  fail("this export takes token embeddings from the run's own encoder (the run has no tokenizer): a page cannot "
       + "make them from audio; stream the tokens with host.py instead");
  throw new Error(page.errors[0]);
}
await warmUp();
buttons.mic.disabled = buttons.file.disabled = false;
page.state = "ready";
statusLine.textContent = `${manifest.model} (${manifest.run}): ${manifest.fps} fps, chunks of ${manifest.chunk_frames} frames, `
  + `${manifest.sample_steps} steps, in the browser (${page.backend})`;
if (query.get("source") === "mic") input.startMicrophone().catch(fail);
