// The browser half of live_view_test.cc: Debian's chromium, driven by playwright-core (from
// web/node_modules), opens prism-client's live view while it streams, waits until the session has
// ended and every chunk is shown, and prints what the page itself decoded and drew as one JSON line.
//   node live_view_browser.mjs URL SCREENSHOT.png WEB_DIR TIMEOUT_MS
import { createRequire } from 'node:module';

const [, , url, screenshot, webDir, timeoutMs] = process.argv;
const require = createRequire(webDir + '/package.json');
const { chromium } = require('playwright-core');

// The flags that work headless on this kind of machine (no GPU: SwiftShader's WebGL; no network
// beyond the loopback: no background connections).
const browser = await chromium.launch({
  executablePath: '/usr/bin/chromium',
  args: ['--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run', '--disable-background-networking',
         '--disable-component-update', '--disable-sync', '--enable-unsafe-swiftshader'],
});
const logs = [];
try {
  const page = await browser.newPage({ viewport: { width: 960, height: 640 } });
  page.on('console', (m) => { if (m.type() === 'error') logs.push(m.text()); });
  page.on('pageerror', (e) => logs.push('page error: ' + e.message));
  await page.goto(url);
  await page.waitForFunction(() => window.prismView && window.prismView.done, null,
                             { timeout: Number(timeoutMs), polling: 200 });
  await page.waitForTimeout(1000); // frames drawn after the last chunk (and the view fitted to it)
  const result = await page.evaluate(async () => {
    const v = window.prismView;
    const api = await (await fetch('api/state')).json();
    return {
      points_decoded: v.pointsDecoded, chunks_decoded: v.chunksDecoded, points_shown: v.pointsShown,
      chunks_shown: v.chunksShown, poses_shown: v.posesShown, states_seen: v.statesSeen, mismatches: v.mismatches,
      errors: v.errors, api_chunk_points: api.chunk_points, api_chunks: api.chunks.length,
      api_map_points: api.map_points, pixels: v.drawnPixels(),
    };
  });
  await page.screenshot({ path: screenshot });
  result.console_errors = logs;
  console.log(JSON.stringify(result));
} catch (e) {
  console.log(JSON.stringify({ failure: String(e), console_errors: logs }));
  process.exitCode = 1;
} finally {
  await browser.close();
}
