// Drives the page `jaxtalk export-model` writes in headless Chromium with a fake microphone fed from a WAV file
// (Chromium loops it). The folder is served by a plain static file server started here (Node's http module: files
// and nothing else); every request it receives and every request the page makes are logged. Opens
// index.html?source=mic&record=1, waits until the page streams, lets it stream for SECONDS of wall time, then
// writes what the page measured to OUT.json: state and errors, each chunk's compute time and capture-to-drawn
// latency, the drawn frames, the RMS of each frame of the audio it captured, that audio (base64 float32), the
// noise it fed the model, the time from the first captured sample to the first drawn frame, and the logs.
// Usage: node stream_page.mjs CHROMIUM WIDTH HEIGHT FOLDER WAV SECONDS OUT.json
// Prints one JSON line: the browser's version, console errors, and counts.
import { createServer } from "node:http";
import { readFile } from "node:fs/promises";
import { writeFileSync } from "node:fs";
import { extname, join, normalize } from "node:path";
import { openPage } from "./browser.mjs";

const [executablePath, width, height, folder, wav, seconds, out] = process.argv.slice(2);
const TYPES = { ".html": "text/html", ".js": "text/javascript", ".mjs": "text/javascript", ".json": "application/json",
                ".wasm": "application/wasm", ".onnx": "application/octet-stream", ".glb": "model/gltf-binary", ".css": "text/css" };
const served = [];
const server = createServer(async (req, res) => {
  const path = normalize(decodeURIComponent(new URL(req.url, "http://x").pathname)).replace(/^(\.\.[/\\])+/, "");
  served.push({ method: req.method, path, upgrade: req.headers.upgrade ?? null });
  try {
    const body = await readFile(join(folder, path === "/" ? "index.html" : path));
    res.writeHead(200, { "Content-Type": TYPES[extname(path)] ?? "application/octet-stream" });
    res.end(body);
  } catch {
    res.writeHead(404);
    res.end();
  }
});
server.on("upgrade", (req, socket) => { served.push({ method: req.method, path: req.url, upgrade: req.headers.upgrade }); socket.destroy(); });
await new Promise((resolve) => server.listen(0, "127.0.0.1", resolve));
const origin = `http://127.0.0.1:${server.address().port}`;

const { browser, page, errors } = await openPage(executablePath, width, height, [
  "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream", `--use-file-for-fake-audio-capture=${wav}`,
  "--autoplay-policy=no-user-gesture-required", "--mute-audio",
]);
const requested = [];
page.on("request", (r) => requested.push(r.url()));
page.on("websocket", (ws) => requested.push(ws.url()));
try {
  await page.goto(`${origin}/index.html?source=mic&record=1`);
  await page.waitForFunction(() => window.jaxtalkStream && ["streaming", "error"].includes(window.jaxtalkStream.state),
                             null, { timeout: 120000 });
  const started = Date.now();
  await page.waitForTimeout(Number(seconds) * 1000);
  const report = await page.evaluate(() => {
    const p = window.jaxtalkStream;
    return { state: p.state, errors: p.errors, manifest: p.manifest, backend: p.backend, chunks: p.chunks, drawn: p.drawn,
             frameRms: p.frameRms, sentSamples: p.sentSamples, audio: p.audioBase64(), noise: p.noise,
             firstFrameMs: p.firstDrawnAt === null ? null : p.firstDrawnAt - p.startedAt,
             status: document.getElementById("status").textContent };
  });
  report.wall = (Date.now() - started) / 1000;
  report.origin = origin;
  report.served = served;
  report.requested = requested;
  writeFileSync(out, JSON.stringify(report));
  console.log(JSON.stringify({ version: browser.version(), errors, state: report.state, chunks: report.chunks.length,
                               drawn: report.drawn.length, sentSamples: report.sentSamples }));
} finally {
  await browser.close();
  server.close();
}
