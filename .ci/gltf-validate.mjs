#!/usr/bin/env node
// Validate .glb/.gltf files with the Khronos glTF-Validator.
// Usage: node .ci/gltf-validate.mjs FILE...
// Prints one summary line per file (plus every error and warning); exits 1 if any file
// has an error or cannot be read, 2 on bad usage. Warnings, infos and hints do not fail.
import { readFile } from 'node:fs/promises';
import { basename, dirname, resolve } from 'node:path';
import { createRequire } from 'node:module';

const validator = createRequire(import.meta.url)('gltf-validator');
const severities = ['error', 'warning', 'info', 'hint'];

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error('usage: node .ci/gltf-validate.mjs FILE...');
  process.exit(2);
}

let failed = false;
for (const file of files) {
  try {
    const report = await validator.validateBytes(new Uint8Array(await readFile(file)), {
      uri: basename(file),
      maxIssues: 0,
      writeTimestamp: false,
      // Resolve relative URIs next to the file (our meshes embed everything, but a
      // stray external reference should be reported, not ignored).
      externalResourceFunction: (uri) =>
        readFile(resolve(dirname(file), decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
    });
    const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
    const info = report.info ?? {};
    console.log(
      `${file}: ${numErrors} errors, ${numWarnings} warnings, ${numInfos} infos, ` +
        `${numHints} hints; ${info.totalVertexCount ?? '?'} vertices, ` +
        `${info.totalTriangleCount ?? '?'} triangles (validator ${report.validatorVersion})`,
    );
    for (const m of messages.filter((m) => m.severity <= 1)) {
      console.log(`  ${severities[m.severity]} ${m.code} at ${m.pointer ?? '-'}: ${m.message}`);
    }
    // Infos and hints only by code, e.g. "info UNUSED_OBJECT ×2".
    const minor = new Map();
    for (const m of messages.filter((m) => m.severity > 1)) {
      const key = `${severities[m.severity]} ${m.code}`;
      minor.set(key, (minor.get(key) ?? 0) + 1);
    }
    for (const [key, n] of minor) console.log(`  ${key} ×${n}`);
    if (numErrors > 0) failed = true;
  } catch (e) {
    console.log(`${file}: cannot validate: ${e}`);
    failed = true;
  }
}
process.exit(failed ? 1 : 0);
