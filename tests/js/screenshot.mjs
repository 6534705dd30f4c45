// Screenshots of pages in headless Chromium, each once `window.jaxtalkReady` is set.
// Usage: node screenshot.mjs CHROMIUM WIDTH HEIGHT URL OUT.png [URL OUT.png ...]
// Prints one JSON line: the browser's version and any console errors the pages logged.
import { openPage } from "./browser.mjs";

const [executablePath, width, height, ...pairs] = process.argv.slice(2);
const { browser, page, errors } = await openPage(executablePath, width, height);
try {
  for (let i = 0; i < pairs.length; i += 2) {
    await page.goto(pairs[i]);
    await page.waitForFunction(() => window.jaxtalkReady === true, null, { timeout: 60000 });
    await page.screenshot({ path: pairs[i + 1] });
  }
  console.log(JSON.stringify({ version: browser.version(), errors }));
} finally {
  await browser.close();
}
