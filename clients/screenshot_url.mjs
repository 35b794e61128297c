// Opens a URL (a local viewer such as `ffrecon view`) in headless Chromium and takes a screenshot once
// the page has settled.
//
//   node screenshot_url.mjs URL OUT.png [WIDTHxHEIGHT] [MAX_WAIT_MS] [MIN_WAIT_MS] [UNCHECKED.png]
//
// Waits for a <canvas>, then screenshots every 750 ms until two in a row are identical (WebGL done
// drawing, data streamed in) after at least MIN_WAIT_MS (default 3000), or MAX_WAIT_MS (default 30000)
// has passed; writes the last one. With UNCHECKED.png, then clicks every checkbox on the page (a viewer's
// layer toggles), waits the same way and writes a second screenshot there. Only http://127.0.0.1 / localhost URLs and data:/blob: are loaded.
// Prints one JSON line: {"stable": bool, "elapsed_ms": n, "canvas": bool, "console_errors": [...], "blocked": [...]}.
import { launchHeadless } from './headless.mjs';
import { writeFileSync } from 'node:fs';

const [url, out_png, size = '1200x800', max_ms = '30000', min_ms = '3000', unchecked_png] = process.argv.slice(2);
if (!url || !out_png) {
  console.error('usage: node screenshot_url.mjs URL OUT.png [WIDTHxHEIGHT] [MAX_WAIT_MS] [MIN_WAIT_MS]');
  process.exit(2);
}
const [width, height] = size.split('x').map(Number);
const browser = await launchHeadless();
const errors = [];
const blocked = [];
const started = Date.now();
try {
  const page = await browser.newPage();
  await page.setViewport({ width, height });
  await page.setRequestInterception(true);
  page.on('request', (req) => {
    const u = req.url();
    if (/^(data|blob):/.test(u) || /^(http|ws)s?:\/\/(127\.0\.0\.1|localhost)(:\d+)?\//.test(u)) return req.continue();
    blocked.push(u);
    return req.abort();
  });
  page.on('console', (msg) => { if (msg.type() === 'error') errors.push(msg.text()); });
  page.on('pageerror', (err) => errors.push(String(err)));
  await page.goto(url, { waitUntil: 'load', timeout: Number(max_ms) });
  let canvas = true;
  try {
    await page.waitForSelector('canvas', { timeout: Number(max_ms) });
  } catch {
    canvas = false;
  }
  const settle = async (limit_ms) => {
    const t0 = Date.now();
    let previous = null;
    let shot = null;
    while (Date.now() - t0 < limit_ms) {
      await new Promise((r) => setTimeout(r, 750));
      shot = Buffer.from(await page.screenshot({ type: 'png' }));
      if (previous && shot.equals(previous) && Date.now() - started >= Number(min_ms)) return [shot, true];
      previous = shot;
    }
    return [shot || Buffer.from(await page.screenshot({ type: 'png' })), false];
  };
  const [shot, stable] = await settle(Number(max_ms) - (Date.now() - started));
  writeFileSync(out_png, shot);
  let unchecked = null;
  if (unchecked_png) {
    // One at a time: a click re-renders the panel, so elements found before it may be stale.
    const clicked = [];
    for (let i = 0; i < 50; i++) {
      const label = await page.evaluate(() => {
        const box = [...document.querySelectorAll('input[type=checkbox]')].find((b) => b.checked && b.offsetParent);
        if (!box) return null;
        const text = ((box.id && document.querySelector(`label[for="${box.id}"]`)?.innerText) || '').trim();
        box.click();
        return text;
      });
      if (label === null) break;
      clicked.push(label);
      await new Promise((r) => setTimeout(r, 300));
    }
    const [hidden, hidden_stable] = await settle(Number(max_ms));
    writeFileSync(unchecked_png, hidden);
    unchecked = { clicked, stable: hidden_stable };
  }
  console.log(JSON.stringify({ stable, elapsed_ms: Date.now() - started, canvas, unchecked, console_errors: errors, blocked }));
} finally {
  await browser.close();
}
