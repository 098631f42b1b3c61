// Build the viewer into the Python package: src/keyshape/viewer/static/viewer.js (one
// minified file, three.js included), so the page needs no network at run time.
//   npm ci && npm run build        (from this folder)

import { readFileSync, statSync } from 'node:fs';
import { dirname, join } from 'node:path';
import { fileURLToPath } from 'node:url';
import * as esbuild from 'esbuild';

const here = dirname(fileURLToPath(import.meta.url));
const outfile = join(here, '..', 'src', 'keyshape', 'viewer', 'static', 'viewer.js');
const three = JSON.parse(readFileSync(join(here, 'node_modules', 'three', 'package.json'), 'utf8')).version;

await esbuild.build({
  entryPoints: [join(here, 'src', 'main.js')],
  outfile,
  bundle: true,
  minify: true,
  format: 'iife',
  target: ['es2020'],
  legalComments: 'eof',
  banner: { js: `/* keyshape viewer, built from viewer/ with esbuild; includes three.js ${three} (MIT licence) */` },
  logLevel: 'warning',
});
console.log(`${outfile}: ${(statSync(outfile).size / 1024).toFixed(0)} KiB`);
