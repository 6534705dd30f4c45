// The one way the tests open headless Chromium: no GPU, no network, so software WebGL and no
// background connections; the page's console errors and uncaught exceptions are collected.
import { chromium } from "playwright-core";

export async function openPage(executablePath, width, height, extraArgs = []) {
  const browser = await chromium.launch({
    executablePath,
    args: ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
           "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
           ...extraArgs],
  });
  const errors = [];
  try {
    const page = await browser.newPage({ viewport: { width: Number(width), height: Number(height) } });
    page.on("console", (m) => { if (m.type() === "error") errors.push(m.text()); });
    page.on("pageerror", (e) => errors.push(String(e)));
    return { browser, page, errors };
  } catch (e) {
    await browser.close();
    throw e;
  }
}
