// The browser app end to end against real servers, the same checks in each browser
// (browser-drivers.mjs says how each is driven):
//
//   node .ci/browser.mjs --browser chromium|firefox --open <URL> --keyed <URL> --key <key>
//        --set <data-set folder> [--shots <screenshot dir>]
//
// On the server without API keys (--open): submits the folder's images and light table
// through the page, waits for the job to succeed, then checks that the relighting canvas
// draws, that it changes when the light is dragged, that the 3-D canvas draws the mesh;
// then a job whose outputs have no mesh.glb, whose 3-D view draws the height map as a
// grid; then a normal map (that job's normal.png) picked and integrated, its mesh drawn;
// then a calibration made over the API, offered in the form and picked for a job that
// runs on its lights; that the page logged no console errors; then that a refused light
// table is shown as the problem's title and detail beside it.
// On the server with a key (--keyed): the page asks for the key before calling the API
// (no console error), says a wrong key is not valid, and with the right key submits and
// shows the result. A refused request is logged by Chromium as "Failed to load resource:
// the server responded with a status of 4xx": those two (the 422 of the refused table, the
// 401 of the wrong key) are the only console errors accepted, each after its step.
// Screenshots go to the given directory only (never into the repository).
import { mkdtempSync, readdirSync, readFileSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { basename, join } from "node:path";
import { parseArgs } from "node:util";
import { launch } from "./browser-drivers.mjs";

const { values: arg } = parseArgs({
  options: {
    browser: { type: "string", default: "chromium" },
    open: { type: "string" },
    keyed: { type: "string" },
    key: { type: "string" },
    set: { type: "string" },
    shots: { type: "string" },
    chrome: { type: "string", default: "res/chrome" },
    glossy: { type: "string", default: "res/glossy" },
  },
});
if (!arg.open || !arg.keyed || !arg.key || !arg.set) {
  console.error("usage: node .ci/browser.mjs --browser chromium|firefox --open <URL> --keyed <URL> --key <key> --set <folder> [--shots <dir>]");
  process.exit(2);
}
const setFiles = (dir) =>
  readdirSync(dir)
    .filter((f) => /\.(png|bmp|jpe?g|tiff?|csv)$/i.test(f))
    .map((f) => join(dir, f));
const files = setFiles(arg.set);

const browser = await launch(arg.browser);
const page = browser.page;
const failures = [];
const check = (ok, what) => {
  console.log(`${ok ? "ok  " : "FAIL"} ${browser.name}: ${what}`);
  if (!ok) failures.push(what);
};
// Console errors logged since `from`, less those `allowed` matches.
const errorsSince = (from, allowed) => page.errors.slice(from).filter((e) => !(allowed && allowed.test(e)));

// Pixel statistics of a canvas: how many are lit, a position-weighted sum (to tell two
// pictures apart) and the brightness of the left and the right half.
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
    const half = [0, 0];
    for (let i = 0; i < p.length; i += 4) {
      if (p[i] > 30) lit++;
      sum += p[i] * ((i / 4) % 251);
      half[(i / 4) % c.width < c.width / 2 ? 0 : 1] += p[i];
    }
    return { lit, total: p.length / 4, sum, half };
  }, id);

const drawn = async (id, share) => {
  for (let i = 0; i < 100; i++) {
    const s = await stats(id);
    if (s.lit > s.total * share) return s;
    await new Promise((ok) => setTimeout(ok, 100));
  }
  return stats(id);
};

// Drop the set's files on the form (ticking `outputs`, if any), submit, wait for the new
// job to end; returns its status and id. The result opens by itself when it succeeds.
async function submitSet(outputs = [], set = files) {
  await page.files("[data-testid=file-input]", set);
  await page.waitFor(() => document.querySelector("#file-list li") && document.getElementById("lights").value.trim());
  for (const name of outputs) await page.click(`#options input[type=checkbox][value="${name}"]`);
  return submitAndWait();
}

// Submit the form as it is and wait for the new job to end; returns its status and id.
async function submitAndWait() {
  const before = await page.evaluate(() => document.querySelectorAll("#jobs tbody tr").length);
  await page.click("[data-testid=submit]");
  await page.waitFor(
    (n) => {
      const rows = document.querySelectorAll("#jobs tbody tr");
      const status = rows.length > n && rows[0].querySelector("[data-testid=job-status]").textContent;
      return /^(succeeded|failed|cancelled)$/.test(status);
    },
    before,
    120_000,
  );
  return page.evaluate(() => {
    const row = document.querySelector("#jobs tbody tr");
    return { status: row.querySelector("[data-testid=job-status]").textContent, id: row.querySelector("code").title };
  });
}

async function resultShown(id, surface) {
  await page.waitFor(
    ([id, surface]) =>
      document.getElementById("result-title").textContent.includes(id.slice(0, 8)) &&
      document.querySelector("#maps canvas") &&
      document.getElementById("mesh-canvas").dataset.surface === surface,
    [id, surface],
  );
}

// A calibration from four of the chrome set's sphere images (its known circle), its lights
// named after the set's images; returns the calibration resource.
async function createCalibration(base) {
  const form = new FormData();
  for (const name of ["ball01.png", "ball02.png", "ball03.png", "ball04.png"]) {
    form.append("images", new Blob([readFileSync(join(arg.chrome, name))], { type: "image/png" }), name);
  }
  const images = files.filter((f) => /\.png$/i.test(f)).map((f) => basename(f));
  form.append("names", images.join("\n"));
  form.append("circle", readFileSync(join(arg.chrome, "truth-lights", "circle.txt"), "utf8").trim());
  const answer = await fetch(`${base}/v1/calibrations`, { method: "POST", body: form });
  if (answer.status !== 201) throw new Error(`POST /v1/calibrations: ${answer.status} ${await answer.text()}`);
  return answer.json();
}

async function rakeFromRight() {
  await page.click('.presets button[data-azimuth="0"]');
}

try {
  // ------------------------------------------------ the open server
  await page.goto(arg.open + "/");
  await page.waitFor(() => document.querySelector("#options select")); // the form is built
  // The console checks below can fail: an error the page logs is seen.
  await page.evaluate(() => console.error("photostereo console probe"));
  for (let i = 0; i < 50 && !page.errors.length; i++) await new Promise((ok) => setTimeout(ok, 100));
  check(page.errors.length === 1 && /console probe/.test(page.errors[0]), `a console error is seen (${page.errors.join(" | ")})`);
  page.errors.length = 0;
  let job = await submitSet();
  check(job.status === "succeeded", `the job's status reaches succeeded (${job.status})`);
  await resultShown(job.id, "mesh");

  const before = await drawn("relight-canvas", 1 / 20);
  check(before.lit > before.total / 20, `the relighting canvas draws (${before.lit} of ${before.total} pixels lit)`);

  // Drag the light from where it is to the far left of the hemisphere (raking from the left).
  const box = await page.box("[data-testid=light-widget]");
  await page.mouse.move(box.x + box.width * 0.7, box.y + box.height * 0.3);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width * 0.4, box.y + box.height * 0.45, 5);
  await page.mouse.move(box.x + box.width * 0.08, box.y + box.height * 0.5, 5);
  await page.mouse.up();
  const after = await stats("relight-canvas");
  check(after.sum !== before.sum && after.lit > 0, `the relighting changes when the light is dragged (${before.lit} -> ${after.lit} lit pixels)`);
  check(after.half[0] > 1.2 * after.half[1], `lit from the left, the left half is the brighter (${after.half})`);
  const azimuth = await page.evaluate(() => document.getElementById("azimuth").value);
  check(Math.abs(Math.abs(+azimuth) - 180) < 20, `the drag moved the light to the left (azimuth ${azimuth}°)`);
  const meshLeft = await drawn("mesh-canvas", 1 / 50);
  await rakeFromRight();
  const right = await stats("relight-canvas");
  check(right.half[1] > 1.2 * right.half[0], `raking from the right, the right half is the brighter (${right.half})`);

  const mesh = await drawn("mesh-canvas", 1 / 50);
  check(mesh.lit > mesh.total / 50, `the 3-D canvas draws the mesh (${mesh.lit} of ${mesh.total} pixels lit)`);
  check(mesh.sum !== meshLeft.sum, "the mesh is lit by the same light (its picture changes with it)");
  const links = await page.evaluate(() => document.querySelectorAll("#downloads a").length);
  check(links >= 5, `download links for the artifacts (${links})`);

  // Dragging on the relit picture moves the light: pointing at its left edge lights from
  // the left, low.
  const canvasBox = await page.box("[data-testid=relight-canvas]");
  await page.mouse.move(canvasBox.x + canvasBox.width * 0.6, canvasBox.y + canvasBox.height * 0.5);
  await page.mouse.down();
  await page.mouse.move(canvasBox.x + canvasBox.width * 0.02, canvasBox.y + canvasBox.height * 0.5, 5);
  await page.mouse.up();
  const dragged = await stats("relight-canvas");
  const draggedTo = await page.evaluate(() => [+document.getElementById("azimuth").value, +document.getElementById("elevation").value]);
  check(
    Math.abs(Math.abs(draggedTo[0]) - 180) < 10 && draggedTo[1] < 20 && dragged.half[0] > 1.2 * dragged.half[1],
    `dragging on the relit picture to its left edge lights it from the left (azimuth ${draggedTo[0]}°, elevation ${draggedTo[1]}°, halves ${dragged.half})`,
  );
  await rakeFromRight();

  if (arg.shots) {
    await page.screenshot("#result", join(arg.shots, "result.png"));
    await page.click('.presets button[data-azimuth="180"]');
    await page.fill("#intensity", "2.5");
    await page.screenshot("[data-testid=relight-canvas]", join(arg.shots, "relight.png"));
    await page.screenshot("[data-testid=mesh-canvas]", join(arg.shots, "mesh.png"));
    await page.screenshot(null, join(arg.shots, "page.png"));
    await page.fill("#intensity", "1");
  }

  // A glossy set with the glossy solver: its fitted highlights show in the relighting, and
  // the switch turns them off (Lambertian shading).
  await page.evaluate(() => {
    const solver = [...document.querySelectorAll("#options select")].find((s) => [...s.options].some((o) => o.value === "glossy"));
    solver.value = "glossy";
    solver.dispatchEvent(new Event("change", { bubbles: true }));
  });
  const glossy = await submitSet([], setFiles(arg.glossy));
  check(glossy.status === "succeeded", `a glossy-solver job succeeds (${glossy.status})`);
  await resultShown(glossy.id, "mesh");
  await page.waitFor(() => !document.getElementById("material-switch").hidden);
  // Light from the camera's side, where the sphere's highlight faces the viewer.
  await page.evaluate(() => {
    document.getElementById("elevation").value = 80;
    document.getElementById("elevation").dispatchEvent(new Event("input"));
  });
  const withLobe = await drawn("relight-canvas", 1 / 500);
  await page.click("#material");
  const lambertian = await stats("relight-canvas");
  // The sphere is dark (albedo about 0.013): Lambertian shading lights almost nothing,
  // its fitted highlight (roughness about 0.16) a patch a few pixels across.
  check(
    withLobe.lit >= lambertian.lit + 8 && withLobe.half[0] + withLobe.half[1] > lambertian.half[0] + lambertian.half[1],
    `the fitted highlights light the relit glossy sphere, and the switch turns them off (${withLobe.lit} against ${lambertian.lit} lit pixels)`,
  );
  await page.click("#material");
  await page.evaluate(() => {
    const solver = [...document.querySelectorAll("#options select")].find((s) => [...s.options].some((o) => o.value === "glossy"));
    solver.value = "robust";
    solver.dispatchEvent(new Event("change", { bubbles: true }));
  });

  // A job without mesh.glb: the 3-D view draws the height map as a grid.
  job = await submitSet(["albedo.png", "normal.png", "height.png", "mask.png", "result.json"]);
  check(job.status === "succeeded", `a job without a mesh succeeds (${job.status})`);
  await resultShown(job.id, "grid");
  const artifacts = await page.evaluate(() => [...document.querySelectorAll("#downloads a")].map((a) => a.textContent));
  check(!artifacts.includes("mesh.glb"), `that job has no mesh.glb (${artifacts.join(", ")})`);
  await rakeFromRight();
  const gridRight = await drawn("mesh-canvas", 1 / 50);
  check(gridRight.lit > gridRight.total / 50, `the 3-D canvas draws the height grid (${gridRight.lit} of ${gridRight.total} pixels lit)`);
  await page.click('.presets button[data-azimuth="180"]');
  const gridLeft = await stats("mesh-canvas");
  check(gridLeft.sum !== gridRight.sum, "the grid is lit by the same light (its picture changes with it)");
  check(
    gridLeft.half[0] > gridLeft.half[1] && gridRight.half[1] > gridRight.half[0],
    `raking from either side, the grid's half on that side is the brighter (left ${gridLeft.half}, right ${gridRight.half})`,
  );
  if (arg.shots) await page.screenshot("[data-testid=mesh-canvas]", join(arg.shots, "grid.png"));

  // A normal map picked instead of the set (that job's normal.png): its job integrates the
  // map, writing the outputs ticked, and the 3-D view draws the mesh it wrote. The ticks
  // left from the job above include albedo.png, which a normals job cannot write: the
  // refusal is shown at the options, naming what it can write.
  const normalMap = join(mkdtempSync(join(tmpdir(), "photostereo-normals-")), "normal.png");
  const normalPng = await fetch(`${arg.open}/v1/jobs/${job.id}/artifacts/normal.png`);
  writeFileSync(normalMap, Buffer.from(await normalPng.arrayBuffer()));
  await page.files("[data-testid=normals-input]", [normalMap]);
  await page.click("[data-testid=submit]");
  await page.waitFor(() => !document.getElementById("problem-options").hidden);
  const outputsRefused = await page.evaluate(() => document.getElementById("problem-options").textContent);
  check(
    /outputs/.test(outputsRefused) && /albedo\.png/.test(outputsRefused) && /mesh\.glb/.test(outputsRefused),
    `outputs a normals job cannot write are refused at the options, naming what it writes (${outputsRefused})`,
  );
  await page.click('#options input[type=checkbox][value="albedo.png"]');
  await page.click('#options input[type=checkbox][value="mesh.glb"]');
  const integrated = await submitAndWait();
  check(integrated.status === "succeeded", `a job of a picked normal map succeeds (${integrated.status})`);
  await resultShown(integrated.id, "mesh");
  const normalsJob = await (await fetch(`${arg.open}/v1/jobs/${integrated.id}`)).json();
  const normalsArtifacts = Object.keys(normalsJob.artifacts || {}).sort().join(", ");
  check(
    normalsJob.image_count === 0 && normalsArtifacts === "height.png, mask.png, mesh.glb, normal.png, result.json",
    `that job integrated the map into heights, writing the outputs ticked (${normalsArtifacts})`,
  );
  const counted = await page.evaluate(() => document.getElementById("summary").textContent);
  const used = normalsJob.result && normalsJob.result.counts && normalsJob.result.counts.used;
  check(used > 0 && counted.includes(`${used} used`), `the summary shows the map's pixel counts (${used}: ${counted})`);
  const normalsMesh = await drawn("mesh-canvas", 1 / 50);
  check(normalsMesh.lit > normalsMesh.total / 50, `the 3-D canvas draws its mesh (${normalsMesh.lit} of ${normalsMesh.total} pixels lit)`);
  const unexpected = errorsSince(0, /status of 422/);
  check(unexpected.length === 0, `no console errors but the refusal's 422${unexpected.length ? ": " + unexpected.join(" | ") : ""}`);
  // Back to the default set for the jobs below.
  await page.evaluate(() => {
    for (const c of document.querySelectorAll("#options input[type=checkbox]:checked")) c.checked = false;
  });

  // A calibration made over the API is offered in the form, and a job that picks it runs
  // on its lights instead of the dropped table (its light matrix differs).
  const tabled = await (await fetch(`${arg.open}/v1/jobs/${job.id}`)).json();
  const calibration = await createCalibration(arg.open);
  await page.goto(arg.open + "/");
  await page.waitFor(
    (id) =>
      !document.getElementById("calibration-field").hidden &&
      [...document.querySelectorAll("#calibration option")].some((o) => o.value === id),
    calibration.id,
  );
  const offered = await page.evaluate(
    (id) => [...document.querySelectorAll("#calibration option")].find((o) => o.value === id).textContent,
    calibration.id,
  );
  check(/· 4 lights/.test(offered), `the calibration is offered in the form (${offered})`);
  await page.evaluate((id) => {
    const select = document.getElementById("calibration");
    select.value = id;
    select.dispatchEvent(new Event("change"));
  }, calibration.id);
  job = await submitSet();
  check(job.status === "succeeded", `a job with the calibration picked succeeds (${job.status})`);
  const calibrated = await (await fetch(`${arg.open}/v1/jobs/${job.id}`)).json();
  const [a, b] = [calibrated, tabled].map((j) => j.result && j.result.light_condition_number);
  check(a > 0 && b > 0 && Math.abs(a - b) > 1e-6, `that job ran on the calibration's lights (condition number ${a} against the table's ${b})`);
  const stillUnexpected = errorsSince(0, /status of 422/);
  check(stillUnexpected.length === 0, `still no console errors but that 422${stillUnexpected.length ? ": " + stillUnexpected.join(" | ") : ""}`);
  await page.evaluate(() => {
    const select = document.getElementById("calibration");
    select.value = "";
    select.dispatchEvent(new Event("change"));
  });

  // A refused submission: the problem's title and detail next to the light table.
  let seen = page.errors.length;
  await page.files("[data-testid=file-input]", files);
  await page.waitFor(() => document.querySelector("#file-list li") && document.getElementById("lights").value.trim());
  const table = await page.evaluate(() => document.getElementById("lights").value);
  await page.fill("#lights", table.replace(/^([^,\n]+),[^,\n]+,/, "$1, east,"));
  await page.click("[data-testid=submit]");
  await page.waitFor(() => !document.getElementById("problem-lights").hidden);
  const shown = await page.evaluate(() => document.getElementById("problem-lights").textContent);
  check(/^Invalid input/.test(shown) && /east/.test(shown) && !shown.includes("{"), `a refused light table is shown next to it (${shown})`);
  let others = errorsSince(seen, /status of 422/);
  check(others.length === 0, `no other console errors (${page.errors.length - seen - others.length} "status of 422" accepted)${others.length ? ": " + others.join(" | ") : ""}`);

  // ------------------------------------------------ the server with an API key
  seen = page.errors.length;
  await page.goto(arg.keyed + "/");
  await page.waitFor(
    () => !document.getElementById("problem-key").hidden && document.activeElement === document.getElementById("api-key"),
  );
  let prompt = await page.evaluate(() => document.getElementById("problem-key").textContent);
  check(/needs an API key/.test(prompt), `with a key required, the page asks for it (${prompt})`);
  others = errorsSince(seen);
  check(others.length === 0, `asking for the key logs no console error${others.length ? ": " + others.join(" | ") : ""}`);

  seen = page.errors.length;
  await page.type("#api-key", "not-the-key");
  await page.press("Enter");
  await page.waitFor(() => /not valid/.test(document.getElementById("problem-key").textContent));
  prompt = await page.evaluate(() => document.getElementById("problem-key").textContent);
  check(/^Missing or invalid API key/.test(prompt) && /not valid/.test(prompt), `a wrong key is said to be not valid (${prompt})`);
  others = errorsSince(seen, /status of 401/);
  const refused = page.errors.length - seen - others.length;
  check(others.length === 0, `a wrong key logs no other console error (${refused} "status of 401" accepted)${others.length ? ": " + others.join(" | ") : ""}`);

  seen = page.errors.length;
  await page.fill("#api-key", arg.key);
  await page.waitFor(() => document.getElementById("problem-key").hidden);
  job = await submitSet();
  check(job.status === "succeeded", `with the key, the job's status reaches succeeded (${job.status})`);
  await resultShown(job.id, "mesh");
  const keyed = await drawn("relight-canvas", 1 / 20);
  check(keyed.lit > keyed.total / 20, `with the key, the relighting canvas draws (${keyed.lit} of ${keyed.total} pixels lit)`);
  const keyedMesh = await drawn("mesh-canvas", 1 / 50);
  check(keyedMesh.lit > keyedMesh.total / 50, `with the key, the 3-D canvas draws (${keyedMesh.lit} of ${keyedMesh.total} pixels lit)`);
  others = errorsSince(seen);
  check(others.length === 0, `with the key, no console errors${others.length ? ": " + others.join(" | ") : ""}`);
} finally {
  await browser.close();
}
if (failures.length) {
  console.error(`${browser.name}: ${failures.length} browser check(s) failed`);
  process.exit(1);
}
