// The browsers the app's checks run in, behind one small page interface so that the
// checks (browser.mjs) are written once:
//
// - chromium: Debian's package driven by playwright-core (Playwright's own browser
//   download is not used);
// - firefox: Debian's firefox-esr driven by puppeteer-core over WebDriver BiDi (Playwright
//   drives only its own patched Firefox). Headless Firefox has no WebGL on Linux (Mozilla
//   bug 1375585: every GL driver option fails, even with webgl.force-enabled), so Firefox
//   runs with a window, on the X display it is given (browser.sh runs it under xvfb-run,
//   where Mesa's llvmpipe renders WebGL2).
//
// A page: goto(url), files(sel, paths), click(sel), fill(sel, text) (replaces the value and
// fires input and change, as typing and leaving the field does), type(sel, text) then
// press(key), evaluate(fn, arg), waitFor(fn, arg, ms) (until fn(arg) is truthy in the page),
// box(sel) (scrolled into view), mouse.{move(x, y, steps), down(), up()},
// screenshot(sel | null, path), and errors (console errors and uncaught exceptions).

import { mkdtempSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";

const VIEWPORT = { width: 1440, height: 1300 };

export async function launch(name) {
  if (name === "chromium") return chromium();
  if (name === "firefox") return firefox();
  throw new Error(`unknown browser ${name} (chromium or firefox)`);
}

function collect(page) {
  const errors = [];
  page.on("console", (m) => m.type() === "error" && errors.push(m.text()));
  page.on("pageerror", (e) => errors.push(String(e)));
  return errors;
}

async function chromium() {
  const { chromium } = await import("playwright-core");
  const profile = mkdtempSync(join(tmpdir(), "photostereo-chromium-"));
  // A fresh profile (Playwright passes it as --user-data-dir).
  const context = await chromium.launchPersistentContext(profile, {
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: true,
    args: [
      "--headless",
      "--no-sandbox",
      "--disable-gpu",
      "--disable-quic",
      "--no-first-run",
      "--disable-background-networking",
      "--disable-component-update",
      "--disable-sync",
    ],
    viewport: VIEWPORT,
  });
  const p = context.pages()[0] || (await context.newPage());
  const page = {
    errors: collect(p),
    goto: (url) => p.goto(url),
    files: (sel, paths) => p.locator(sel).setInputFiles(paths),
    click: (sel) => p.locator(sel).click(),
    fill: (sel, text) => p.locator(sel).fill(text).then(() => p.locator(sel).dispatchEvent("change")),
    type: (sel, text) => p.locator(sel).pressSequentially(text),
    press: (key) => p.keyboard.press(key),
    evaluate: (fn, arg) => p.evaluate(fn, arg),
    waitFor: (fn, arg, ms = 30_000) => p.waitForFunction(fn, arg, { timeout: ms }),
    box: async (sel) => {
      await p.locator(sel).scrollIntoViewIfNeeded();
      return p.locator(sel).boundingBox();
    },
    mouse: {
      move: (x, y, steps = 1) => p.mouse.move(x, y, { steps }),
      down: () => p.mouse.down(),
      up: () => p.mouse.up(),
    },
    screenshot: (sel, path) => (sel ? p.locator(sel).screenshot({ path }) : p.screenshot({ path, fullPage: true })),
  };
  return {
    name: "Chromium",
    page,
    close: async () => {
      await context.close();
      rmSync(profile, { recursive: true, force: true });
    },
  };
}

async function firefox() {
  const { default: puppeteer } = await import("puppeteer-core");
  const browser = await puppeteer.launch({
    browser: "firefox",
    protocol: "webDriverBiDi",
    executablePath: process.env.FIREFOX || "/usr/bin/firefox-esr",
    headless: false,
    defaultViewport: VIEWPORT,
    args: [`--width=${VIEWPORT.width}`, `--height=${VIEWPORT.height + 150}`],
    extraPrefsFirefox: {
      // Mesa's software renderer is on no allow-list; nothing else is reached.
      "webgl.force-enabled": true,
      "network.captive-portal-service.enabled": false,
      "app.normandy.enabled": false,
      "messaging-system.rsexperimentloader.enabled": false,
    },
  });
  const p = (await browser.pages())[0] || (await browser.newPage());
  const setValue = (sel, text) =>
    p.$eval(
      sel,
      (el, text) => {
        el.value = text;
        el.dispatchEvent(new Event("input", { bubbles: true }));
        el.dispatchEvent(new Event("change", { bubbles: true }));
      },
      text,
    );
  const page = {
    errors: collect(p),
    goto: (url) => p.goto(url),
    files: async (sel, paths) => (await p.waitForSelector(sel)).uploadFile(...paths),
    click: (sel) => p.click(sel),
    fill: setValue,
    type: (sel, text) => p.type(sel, text),
    press: (key) => p.keyboard.press(key),
    evaluate: (fn, arg) => p.evaluate(fn, arg),
    waitFor: (fn, arg, ms = 30_000) => p.waitForFunction(fn, { timeout: ms, polling: 100 }, arg),
    box: async (sel) => {
      const el = await p.waitForSelector(sel);
      await el.scrollIntoView();
      return el.boundingBox();
    },
    mouse: {
      move: (x, y, steps = 1) => p.mouse.move(x, y, { steps }),
      down: () => p.mouse.down(),
      up: () => p.mouse.up(),
    },
    screenshot: async (sel, path) => (sel ? (await p.$(sel)).screenshot({ path }) : p.screenshot({ path, fullPage: true })),
  };
  return { name: "Firefox", page, close: () => browser.close() };
}
