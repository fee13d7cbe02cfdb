// The browser app end to end in headless Chromium (Debian's package, driven by
// playwright-core; Playwright's own browser download is not used):
//
//   node .ci/browser.mjs <base URL> <data-set folder> [<screenshot dir>]
//
// Submits the folder's images and light table through the page, waits for the job to
// succeed, then checks that the relighting canvas draws, that it changes when the light is
// dragged, that the 3-D canvas draws, and that the page logged no console errors; then
// that a refused light table is shown as the problem's title and detail beside it.
// Screenshots go to the given directory only (never into the repository).
import { chromium } from "playwright-core";
import { mkdtempSync, readdirSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";

const [base, set, shots] = process.argv.slice(2);
if (!base || !set) {
  console.error("usage: node .ci/browser.mjs <base URL> <data-set folder> [<screenshot dir>]");
  process.exit(2);
}
const files = readdirSync(set)
  .filter((f) => /\.(png|bmp|jpe?g|tiff?|csv)$/i.test(f))
  .map((f) => join(set, f));

const profile = mkdtempSync(join(tmpdir(), "photostereo-chromium-"));
// A fresh profile (Playwright passes it as --user-data-dir).
const browser = await chromium.launchPersistentContext(profile, {
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
  viewport: { width: 1440, height: 1300 },
});
const failures = [];
const check = (ok, what) => {
  console.log(`${ok ? "ok  " : "FAIL"} ${what}`);
  if (!ok) failures.push(what);
};
try {
  const page = browser.pages()[0] || (await browser.newPage());
  const errors = [];
  page.on("console", (m) => m.type() === "error" && errors.push(m.text()));
  page.on("pageerror", (e) => errors.push(String(e)));

  await page.goto(base + "/");
  await page.locator("#options select").first().waitFor(); // the form is built
  await page.getByTestId("file-input").setInputFiles(files);
  await page.getByTestId("submit").click();
  const status = page.getByTestId("job-status").first();
  await status.filter({ hasText: /^(succeeded|failed|cancelled)$/ }).waitFor({ timeout: 120_000 });
  check((await status.textContent()) === "succeeded", `the job's status reaches succeeded (${await status.textContent()})`);

  // The result opens by itself once the job has succeeded; wait for both views to draw.
  await page.locator("#maps canvas").first().waitFor();
  const stats = (id) =>
    page.evaluate((id) => {
      const src = document.getElementById(id);
      const c = document.createElement("canvas");
      c.width = src.width;
      c.height = src.height;
      const g = c.getContext("2d");
      g.drawImage(src, 0, 0);
      const p = g.getImageData(0, 0, c.width, c.height).data;
      let lit = 0;
      let sum = 0;
      const half = [0, 0]; // brightness of the left and the right half
      for (let i = 0; i < p.length; i += 4) {
        if (p[i] > 30) lit++;
        sum += p[i] * ((i / 4) % 251);
        half[(i / 4) % c.width < c.width / 2 ? 0 : 1] += p[i];
      }
      return { lit, total: p.length / 4, sum, half };
    }, id);
  const drawn = async (id) => {
    for (let i = 0; i < 100; i++) {
      const s = await stats(id);
      if (s.lit > s.total / 20) return s;
      await page.waitForTimeout(100);
    }
    return stats(id);
  };
  const before = await drawn("relight-canvas");
  check(before.lit > before.total / 20, `the relighting canvas draws (${before.lit} of ${before.total} pixels lit)`);

  // Drag the light from where it is to the far left of the hemisphere (raking from the left).
  const widget = page.getByTestId("light-widget");
  await widget.scrollIntoViewIfNeeded();
  const box = await widget.boundingBox();
  await page.mouse.move(box.x + box.width * 0.7, box.y + box.height * 0.3);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width * 0.4, box.y + box.height * 0.45, { steps: 5 });
  await page.mouse.move(box.x + box.width * 0.08, box.y + box.height * 0.5, { steps: 5 });
  await page.mouse.up();
  const after = await stats("relight-canvas");
  check(after.sum !== before.sum && after.lit > 0, `the relighting changes when the light is dragged (${before.lit} -> ${after.lit} lit pixels)`);
  check(after.half[0] > 1.2 * after.half[1], `lit from the left, the left half is the brighter (${after.half})`);
  const azimuth = await page.locator("#azimuth").inputValue();
  check(Math.abs(Math.abs(+azimuth) - 180) < 20, `the drag moved the light to the left (azimuth ${azimuth}°)`);
  await page.getByRole("button", { name: "from right" }).click();
  const right = await stats("relight-canvas");
  check(right.half[1] > 1.2 * right.half[0], `raking from the right, the right half is the brighter (${right.half})`);

  const mesh = await drawn("mesh-canvas");
  check(mesh.lit > mesh.total / 50, `the 3-D canvas draws (${mesh.lit} of ${mesh.total} pixels lit)`);
  const links = await page.locator("#downloads a").count();
  check(links >= 5, `download links for the artifacts (${links})`);

  if (shots) {
    await page.locator("#result").screenshot({ path: join(shots, "result.png") });
    await page.getByRole("button", { name: "Raking from left" }).click();
    await page.locator("#intensity").fill("2.5");
    await page.getByTestId("relight-canvas").screenshot({ path: join(shots, "relight.png") });
    await page.getByTestId("mesh-canvas").screenshot({ path: join(shots, "mesh.png") });
    await page.screenshot({ path: join(shots, "page.png"), fullPage: true });
  }
  check(errors.length === 0, `no console errors${errors.length ? ": " + errors.join(" | ") : ""}`);

  // A refused submission: the problem's title and detail next to the light table. The
  // browser itself logs the 422 response; nothing else may show.
  await page.getByTestId("file-input").setInputFiles(files);
  const table = await page.locator("#lights").inputValue();
  await page.locator("#lights").fill(table.replace(/^([^,\n]+),[^,\n]+,/, "$1, east,"));
  await page.getByTestId("submit").click();
  const problem = page.locator("#problem-lights");
  await problem.waitFor();
  const shown = await problem.textContent();
  check(/^Invalid input/.test(shown) && /east/.test(shown) && !shown.includes("{"), `a refused light table is shown next to it (${shown})`);

  const others = errors.filter((e) => !/status of 422/.test(e));
  check(others.length === 0, `no other console errors${others.length ? ": " + others.join(" | ") : ""}`);
} finally {
  await browser.close();
  rmSync(profile, { recursive: true, force: true });
}
if (failures.length) {
  console.error(`${failures.length} browser check(s) failed`);
  process.exit(1);
}
