// `jaxtalk view --live`: the microphone (or a file) streamed to `jaxtalk serve`, the face driven by the frames
// that come back, and the measured latency.
//
// The face is the file the server's `morph` output drives (GET /face.glb on the server): its morph targets
// take the weights by name, its `jaw` and `neck` nodes the rotations. Audio goes through an AudioWorklet
// (capture.js: mono, 16 kHz) in messages of `send_ms` (default 40 ms) of float samples; each message is
// stamped with its capture time (when the page received it from the audio graph). Frames come back in
// chunks; each chunk's first frame is drawn as soon as it arrives and the others a frame period apart
// (frames of an older chunk not drawn by then are skipped: the newest motion wins), and the latency of
// a chunk is the time from the capture of the audio message that completed it to the drawing of its
// first frame.
//
// Query: ?server=ws://HOST:PORT (default: the one `jaxtalk view --live --server` names), ?source=mic
// (start the microphone at once), ?send_ms=40. `window.jaxtalkLive` exposes the state, per-chunk latencies
// and the drawn frames (what the browser test reads).
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { stage } from "/stage.js";
import { audioInput } from "/sources.js";

const RATE = 16000;
const KEEP_FRAMES = 3000; // drawn frames kept for inspection (two minutes at 25 fps)
const KEEP_AUDIO = 60 * RATE; // sent audio kept for inspection

const query = new URLSearchParams(location.search);
const config = await (await fetch("/live.json")).json();
const serverUrl = query.get("server") ?? config.server;
const sendSamples = Math.round(RATE * Number(query.get("send_ms") ?? 40) / 1000);
const statusLine = document.getElementById("status");
const buttons = { mic: document.getElementById("mic"), file: document.getElementById("file"), stop: document.getElementById("stop") };

const live = {
  state: "loading", server: serverUrl, errors: [], ready: null, chunks: [], drawn: [], sentSamples: 0, dropped: 0,
  sentMessages: 0, replies: 0, receivedFrames: 0, skipped: 0,
  audio: new Float32Array(KEEP_AUDIO), frameRms: [],
  audioBase64() {
    const bytes = new Uint8Array(this.audio.buffer, 0, 4 * Math.min(this.sentSamples, KEEP_AUDIO));
    let text = "";
    for (let i = 0; i < bytes.length; i += 0x8000) text += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
    return btoa(text);
  },
};
window.jaxtalkLive = live;
const fail = (message) => { live.errors.push(String(message)); live.state = "error"; statusLine.textContent = `error: ${message}`; };

// ------------------------------------------------------------------ the face
let gltf;
try {
  gltf = await new GLTFLoader().loadAsync(serverUrl.replace(/^ws/, "http") + "/face.glb");
} catch (e) {
  fail(`cannot load the face from ${serverUrl}: is \`jaxtalk serve\` running there? (${e.message ?? e})`);
  throw e;
}
const { renderer, draw } = stage(document.getElementById("scene"), gltf.scene);
let mesh = null;
gltf.scene.traverse((o) => { if (o.morphTargetDictionary && !mesh) mesh = o; });
const joints = { jaw: gltf.scene.getObjectByName("jaw"), neck: gltf.scene.getObjectByName("neck") };

// Channel layout of the morph output, from the server's ready message.
let targets = null; // [channel index, morph target index] pairs
let quatAt = null; // joint -> first channel of its quaternion

function apply(values) {
  for (const [c, t] of targets) mesh.morphTargetInfluences[t] = values[c];
  for (const [joint, at] of Object.entries(quatAt)) joints[joint].quaternion.set(values[at], values[at + 1], values[at + 2], values[at + 3]);
}

// ------------------------------------------------------------------ the connection
const queue = []; // frames waiting to be drawn: {frame, values, due, first, seq}
const sent = new Map(); // seq -> capture time (ms) of each audio message
let seq = 0;
let fps = 25;
let chunkFrames = 4;

const ws = new WebSocket(serverUrl);
ws.binaryType = "arraybuffer";
ws.onerror = () => fail(`no connection to ${serverUrl}: is \`jaxtalk serve\` running there?`);
ws.onclose = (e) => { if (live.state !== "error") { live.state = "closed"; statusLine.textContent = `connection closed (${e.code} ${e.reason})`; } };
ws.onopen = () => ws.send(JSON.stringify({ type: "hello", sample_rate: RATE, format: "f32le", outputs: ["morph"] }));
ws.onmessage = (event) => {
  const m = JSON.parse(event.data);
  if (m.type === "ready") onReady(m);
  else if (m.type === "frames") onFrames(m);
  else if (m.type === "error") { live.errors.push(`${m.code}: ${m.message}`); statusLine.textContent = `server: ${m.message}`; }
};

function onReady(m) {
  const channels = m.outputs.morph.channels;
  targets = [];
  quatAt = {};
  channels.forEach((name, c) => {
    if (name.endsWith(".qx")) quatAt[name.slice(0, -3)] = c;
    else if (!name.includes(".q")) {
      const t = mesh.morphTargetDictionary[name];
      if (t === undefined) throw new Error(`the face has no morph target ${name}`);
      targets.push([c, t]);
    }
  });
  fps = m.fps;
  chunkFrames = m.chunk_frames;
  live.ready = m;
  live.state = "ready";
  buttons.mic.disabled = buttons.file.disabled = false;
  statusLine.textContent = `connected to ${serverUrl}: ${m.model}, ${fps} fps, chunks of ${chunkFrames} frames`;
  if (query.get("source") === "mic") input.startMicrophone().catch(fail);
}

function onFrames(m) {
  const now = performance.now();
  live.dropped = m.dropped;
  live.replies += 1;
  live.receivedFrames += m.count;
  if (m.count === 0) return;
  // Newest first: frames of older replies not drawn yet are dropped (in a steady stream the previous chunk
  // has just played out), and of a reply of several chunks the last two are played. The first frame is
  // drawn at once, the others a frame period apart.
  live.skipped += queue.length + Math.max(0, m.count - 2 * chunkFrames);
  queue.length = 0;
  const rows = m.outputs.morph.slice(-2 * chunkFrames);
  const first = m.frame0 + m.count - rows.length;
  const period = 1000 / m.fps;
  rows.forEach((values, i) => queue.push({ frame: first + i, values, due: now + i * period, first: i === 0, seq: m.seq,
                                           compute: m.compute_ms }));
  for (const old of sent.keys()) { if (old < m.seq - 200) sent.delete(old); else break; }
}

// ------------------------------------------------------------------ audio
function send(samples) {
  const captured = performance.now();
  if (ws.readyState !== WebSocket.OPEN || live.ready === null) return;
  seq += 1;
  live.sentMessages = seq;
  sent.set(seq, captured);
  const start = live.sentSamples;
  if (start + samples.length <= KEEP_AUDIO) live.audio.set(samples, start);
  live.sentSamples += samples.length;
  // RMS of every whole 640-sample (one 25-fps frame) stretch sent so far, for the test to compare with.
  for (let f = Math.floor(start / 640); (f + 1) * 640 <= live.sentSamples && (f + 1) * 640 <= KEEP_AUDIO; f++) {
    if (live.frameRms[f] !== undefined) continue;
    let sum = 0;
    for (let s = f * 640; s < (f + 1) * 640; s++) sum += live.audio[s] * live.audio[s];
    live.frameRms[f] = Math.sqrt(sum / 640);
  }
  ws.send(samples.buffer);
}

const input = audioInput({
  rate: RATE, block: sendSamples, worklet: "/capture.js", buttons, onBlock: send, fail,
  onStart: () => { live.state = "streaming"; },
  onStop: () => {
    if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ type: "end" }));
    live.state = "ready";
  },
});

// ------------------------------------------------------------------ drawing
const median = (xs) => { const s = [...xs].sort((a, b) => a - b); return s.length ? s[Math.floor(s.length / 2)] : NaN; };

renderer.setAnimationLoop(() => {
  const now = performance.now();
  let show = null;
  const firsts = [];
  while (queue.length && queue[0].due <= now) {
    show = queue.shift();
    if (show.first) firsts.push(show);
  }
  if (show) apply(show.values);
  draw();
  if (!show) return;
  const drawn = performance.now();
  for (const f of firsts) {
    const captured = sent.get(f.seq);
    if (captured !== undefined) {
      live.chunks.push({ seq: f.seq, frame: f.frame, latency_ms: drawn - captured, compute_ms: f.compute });
      if (live.chunks.length > KEEP_FRAMES) live.chunks.shift();
    }
  }
  const q = show.values.slice(quatAt.jaw, quatAt.jaw + 4);
  // The jaw's rotation angle (from the vector part: accurate for small angles too).
  live.drawn.push({ frame: show.frame, at: drawn, jaw: 2 * Math.atan2(Math.hypot(q[0], q[1], q[2]), Math.abs(q[3])),
                    values: show.values });
  if (live.drawn.length > KEEP_FRAMES) live.drawn.shift();
  const recent = live.chunks.slice(-50);
  statusLine.textContent = `capture→drawn ${median(recent.map((c) => c.latency_ms)).toFixed(0)} ms (median of ${recent.length})`
    + `  server compute ${median(recent.map((c) => c.compute_ms)).toFixed(1)} ms  frame ${show.frame}`
    + (live.dropped ? `  dropped ${live.dropped}` : "");
});
live.state = live.state === "loading" ? "connecting" : live.state;
