// Render splat files with Spark (three.js) in headless Chromium, from one pinhole camera.
//
//   node spark_render.mjs job.json
//
// job.json: {"chromium": "/usr/bin/chromium", "width": W, "height": H, "fx", "fy", "cx", "cy",
//            "cam_from_world": [[r00, r01, r02, t0], [..], [..]]  (OpenCV, world -> camera),
//            "background": [r, g, b] (0..1), "eps2d": 0.3,
//            "renders": [{"splat": "/abs/splat.ply", "out": "/abs/out.png"}, ...]}
// Writes each PNG (W x H, the canvas's own pixels) and prints one JSON line per render
// ({"out", "numSplats", "activeSplats", "seconds"}). The page (spark_page.html) and node_modules are
// served from 127.0.0.1 on an ephemeral port: ES modules and Spark's WASM do not load from file://.
import { createReadStream, readFileSync, statSync, writeFileSync } from "node:fs";
import http from "node:http";
import path from "node:path";
import { fileURLToPath } from "node:url";
import { launchHeadless } from "./headless.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));
const job = JSON.parse(readFileSync(process.argv[2], "utf8"));
const types = {
  ".html": "text/html", ".js": "text/javascript", ".mjs": "text/javascript", ".wasm": "application/wasm",
  ".json": "application/json", ".map": "application/json",
};

// "/splat/<i>/<name>" serves job.renders[i].splat (the extension tells Spark the format);
// anything else is a file under clients/.
function resolve(urlPath) {
  const m = urlPath.match(/^\/splat\/(\d+)\//);
  if (m) return job.renders[Number(m[1])]?.splat;
  const file = path.normalize(path.join(here, decodeURIComponent(urlPath)));
  return file.startsWith(here + path.sep) ? file : undefined;
}

const server = http.createServer((req, res) => {
  const file = resolve(new URL(req.url, "http://localhost").pathname);
  let size;
  try {
    size = file && statSync(file).isFile() ? statSync(file).size : undefined;
  } catch {
    size = undefined;
  }
  if (size === undefined) {
    res.writeHead(404).end();
    return;
  }
  const type = types[path.extname(file)] ?? "application/octet-stream";
  res.writeHead(200, { "Content-Type": type, "Content-Length": size });
  createReadStream(file).pipe(res);
});
await new Promise((ok) => server.listen(0, "127.0.0.1", ok));
const origin = `http://127.0.0.1:${server.address().port}`;

const browser = await launchHeadless(job.chromium ?? undefined);
let failed = false;
const problems = [];
try {
  const page = await browser.newPage();
  page.on("pageerror", (err) => problems.push(`page error: ${err.message}`));
  page.on("console", (msg) => {
    if (msg.type() === "error") problems.push(`console error: ${msg.text()}`);
  });
  page.on("requestfailed", (req) => problems.push(`request failed: ${req.url()}`));
  page.on("response", (res) => {
    if (res.status() >= 400) problems.push(`HTTP ${res.status()}: ${res.url()}`);
  });
  await page.setViewport({ width: job.width, height: job.height, deviceScaleFactor: 1 });
  await page.goto(`${origin}/spark_page.html`);
  await page.waitForFunction("window.sparkPageReady === true", { timeout: 30000 });
  for (const [i, render] of job.renders.entries()) {
    const start = Date.now();
    const url = `${origin}/splat/${i}/${path.basename(render.splat)}`;
    const { png, info } = await page.evaluate((j) => window.renderSplat(j), { ...job, renders: undefined, url });
    writeFileSync(render.out, Buffer.from(png.split(",")[1], "base64"));
    console.log(JSON.stringify({ out: render.out, ...info, seconds: (Date.now() - start) / 1000, problems }));
  }
} catch (err) {
  console.error(`spark_render: ${err.stack ?? err}\n${problems.join("\n")}`);
  failed = true;
} finally {
  await browser.close();
  server.close();
}
process.exit(failed ? 1 : 0);
