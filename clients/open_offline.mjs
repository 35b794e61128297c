// Opens a local HTML file in headless Chromium with the network cut off, and says what it asked for.
//
//   node open_offline.mjs PAGE.html OUT.png [WIDTH HEIGHT] [SELECTOR]
//
// Every request to anything but file:, data: and blob: URLs is recorded and aborted (so a page that
// needs the network shows it). Once the page has loaded, waits (at most 20 s) for SELECTOR, lets
// WebGL draw, scrolls SELECTOR into view and takes a screenshot. Prints one JSON line:
// {"external_requests": [...], "found": bool, "console_errors": [...], "webgl": "..."}.
import { launchHeadless } from './headless.mjs';
import { pathToFileURL } from 'node:url';
import path from 'node:path';

const [page_path, out_png, width = '1100', height = '800', selector = 'body'] = process.argv.slice(2);
const browser = await launchHeadless();
const external = [];
const errors = [];
try {
  const page = await browser.newPage();
  await page.setViewport({ width: Number(width), height: Number(height) });
  await page.setRequestInterception(true);
  page.on('request', (req) => {
    const url = req.url();
    if (/^(file|data|blob):/.test(url)) return req.continue();
    external.push(url);
    return req.abort();
  });
  page.on('console', (msg) => { if (msg.type() === 'error') errors.push(msg.text()); });
  page.on('pageerror', (err) => errors.push(String(err)));
  await page.goto(pathToFileURL(path.resolve(page_path)).href, { waitUntil: 'load', timeout: 60000 });
  let found = true;
  try {
    await page.waitForSelector(selector, { timeout: 20000 });
    await page.$eval(selector, (el) => el.scrollIntoView());
  } catch {
    found = false;
  }
  await new Promise((r) => setTimeout(r, 1500));
  const webgl = await page.evaluate(() => {
    const gl = document.createElement('canvas').getContext('webgl');
    return gl ? gl.getParameter(gl.VERSION) : 'none';
  });
  await page.screenshot({ path: out_png });
  console.log(JSON.stringify({ external_requests: external, found, console_errors: errors, webgl }));
} finally {
  await browser.close();
}
