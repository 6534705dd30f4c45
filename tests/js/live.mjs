// Drives `jaxtalk view --live`'s page in headless Chromium with a fake microphone fed from a WAV file (Chromium
// loops it): opens URL?source=mic, waits until the page streams, lets it stream for SECONDS of wall time,
// then writes what the page measured to OUT.json: its state and errors, the server's ready message, each
// chunk's capture-to-drawn latency, the drawn frames (frame index, jaw angle, every channel's value), the
// RMS of each 25-fps frame of the audio it sent, and that audio (base64 float32).
// Usage: node live.mjs CHROMIUM WIDTH HEIGHT URL WAV SECONDS OUT.json
// Prints one JSON line: the browser's version, console errors, and counts.
import { writeFileSync } from "node:fs";
import { openPage } from "./browser.mjs";

const [executablePath, width, height, url, wav, seconds, out] = process.argv.slice(2);
const { browser, page, errors } = await openPage(executablePath, width, height, [
  "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream", `--use-file-for-fake-audio-capture=${wav}`,
  "--autoplay-policy=no-user-gesture-required", "--mute-audio",
]);
try {
  await page.goto(`${url}${url.includes("?") ? "&" : "?"}source=mic`);
  await page.waitForFunction(() => window.jaxtalkLive && ["streaming", "error"].includes(window.jaxtalkLive.state),
                             null, { timeout: 60000 });
  const started = Date.now();
  await page.waitForTimeout(Number(seconds) * 1000);
  const report = await page.evaluate(() => {
    const live = window.jaxtalkLive;
    return { state: live.state, errors: live.errors, ready: live.ready, chunks: live.chunks, drawn: live.drawn,
             frameRms: live.frameRms, sentSamples: live.sentSamples, dropped: live.dropped, audio: live.audioBase64(),
             sentMessages: live.sentMessages, replies: live.replies, receivedFrames: live.receivedFrames, skipped: live.skipped,
             status: document.getElementById("status").textContent };
  });
  report.wall = (Date.now() - started) / 1000;
  writeFileSync(out, JSON.stringify(report));
  console.log(JSON.stringify({ version: browser.version(), errors, state: report.state, chunks: report.chunks.length,
                               drawn: report.drawn.length, sentSamples: report.sentSamples }));
} finally {
  await browser.close();
}
