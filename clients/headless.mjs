// Headless Chromium as every script here starts it: Debian's build (no browser download), WebGL2 on
// SwiftShader so that three.js, Spark, plotly and viser draw without a GPU.
import puppeteer from 'puppeteer-core';

export function launchHeadless(executablePath = process.env.CHROMIUM || '/usr/bin/chromium') {
  return puppeteer.launch({
    executablePath,
    headless: true,
    args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
}
