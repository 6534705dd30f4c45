// Plays `jaxtalk view`'s page in headless Chromium: waits for the page, presses Play, lets it play for
// SECONDS of wall time, presses Pause, and photographs the paused picture (controls hidden).
// Usage: node playback.mjs CHROMIUM WIDTH HEIGHT URL SECONDS OUT.png
// Prints one JSON line: the browser's version, console errors, the page's clock once paused (audio time
// and the time last drawn) and the wall time from before the Play click to after the pause.
import { openPage } from "./browser.mjs";

const [executablePath, width, height, url, seconds, out] = process.argv.slice(2);
// No sound card: a muted (but running) audio clock.
const { browser, page, errors } = await openPage(executablePath, width, height,
                                                 ["--mute-audio", "--autoplay-policy=no-user-gesture-required"]);
try {
  await page.goto(url);
  await page.waitForFunction(() => window.jaxtalkReady === true, null, { timeout: 60000 });
  // The wall time brackets the whole play: from before the Play click is sent to after the page says
  // it has paused. Timing from when the page is first seen playing would start late by a round trip
  // to the browser, which on a loaded machine is long (CI measured 0.5 s), while the audio already runs.
  const started = Date.now();
  await page.click("#play");
  await page.waitForFunction(() => window.jaxtalkClock().playing, null, { timeout: 30000 });
  await page.waitForTimeout(Number(seconds) * 1000);
  await page.click("#play");
  await page.waitForFunction(() => !window.jaxtalkClock().playing, null, { timeout: 30000 });
  const wall = (Date.now() - started) / 1000;
  // Two more animation frames: the paused time is drawn and composited.
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const clock = await page.evaluate(() => window.jaxtalkClock());
  const label = await page.textContent("#status");
  await page.evaluate(() => document.body.classList.add("still"));
  await page.screenshot({ path: out });
  console.log(JSON.stringify({ version: browser.version(), errors, clock, wall, label }));
} finally {
  await browser.close();
}
