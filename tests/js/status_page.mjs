// The status page in a real headless Chromium (Debian's /usr/bin/chromium, driven by
// playwright-core; Playwright's own browsers are never downloaded). Prints one JSON line per
// phase on stdout; the test (tests/test_status_page.py) acts on the service between phases.
//
// Usage: node status_page.mjs URL SCREENSHOT SCENARIO
//   SCENARIO "alarm": the page plots, updates live ("live"); the test then makes the service
//     refuse a reload; the banner shows RELOAD_FAILED, screenshot ("alarm").
//   SCENARIO "token": the service asks for the token (THERMOCOMP_STATUS_TOKEN here too):
//     without it refused ("no_token"); with ?token= it plots ("token"); the test stops the
//     service: "unreachable" (screenshot); starts it again: "recovered".
//   SCENARIO "not_writing": a service whose link is down: the state bar and the header say so
//     (screenshot, "not_writing").
//   SCENARIO "stopped": compensating ("live"); the test publishes the clean stop's status
//     ("stopped"), then closes the service: the page keeps saying what the control holds ("gone").
// Every wait is for a condition with a generous timeout: nothing here compares clocks.
import { chromium } from "playwright-core";

const [url, shot, scenario = "alarm"] = process.argv.slice(2);
const WAIT_MS = 90_000;
const t0 = performance.now();  // for the log only: how long each phase took
const emit = (phase, data) => console.log(JSON.stringify({ phase, ms: Math.round(performance.now() - t0), ...data }));

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,  // Playwright adds --headless and a fresh temporary --user-data-dir
  args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--no-proxy-server"],
});
// What the page exposes, and what a person would see: the canvas' coloured pixels (the grid and
// the axes are grey; only the plotted series are saturated) and the banner's rendered text.
const look = (page) => page.evaluate(() => {
  const c = document.getElementById("plot");
  const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
  let colored = 0, red = 0;
  for (let i = 0; i < d.length; i += 4) {
    const hi = Math.max(d[i], d[i + 1], d[i + 2]), lo = Math.min(d[i], d[i + 1], d[i + 2]);
    if (hi - lo > 60) colored++;
    if (d[i] > 180 && d[i + 1] < 80 && d[i + 2] < 80) red++;
  }
  const banner = document.getElementById("alarms"), off = document.getElementById("offline");
  return { ...window.thermocomp, colored_pixels: colored, red_pixels: red,
           banner: banner.innerText, banner_bg: getComputedStyle(banner).backgroundColor,
           offline: off.hidden ? null : off.innerText, conn: document.getElementById("conn").innerText };
});
const until = (page, fn, arg) => page.waitForFunction(fn, arg, { timeout: WAIT_MS, polling: 100 });
const plotted = (page) => until(page, () => window.thermocomp && window.thermocomp.plotted > 10)
  .then(() => page.waitForFunction(() => {  // drawn, not only counted
    const c = document.getElementById("plot"), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < d.length; i += 4) if (Math.max(d[i], d[i + 1], d[i + 2]) - Math.min(d[i], d[i + 1], d[i + 2]) > 60) n++;
    return n > 150;  // the grid, the axes and the labels are grey: 0 without data
  }, null, { timeout: WAIT_MS, polling: 250 }));

let failed = false;
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(String(e)));
  if (scenario === "alarm") {
    const resp = await page.goto(url);
    await plotted(page);
    const first = await look(page);
    // live: more history fetched and more points held than at the first paint
    await until(page, ([u, p]) => window.thermocomp.updates > u && window.thermocomp.points > p,
                [first.updates, first.points]);
    const now = await look(page);
    emit("live", { document_status: resp.status(), first, now, errors });
    await until(page, () => window.thermocomp.alarms.includes("RELOAD_FAILED"));
    // its band under the time axis: drawn once the history that holds it has come (the alarm
    // stays raised, so each new point adds to the count)
    await until(page, (n) => window.thermocomp.banded > n, now.banded);
    await page.locator("#alarms", { hasText: "RELOAD_FAILED" }).waitFor({ state: "visible", timeout: WAIT_MS });
    await page.screenshot({ path: shot });
    emit("alarm", { ...(await look(page)), screenshot: shot, errors });
  } else if (scenario === "token") {
    const token = process.env.THERMOCOMP_STATUS_TOKEN;
    const base = new URL(url);
    // Chromium turns an empty 401 into an error page (goto rejects): its response still counts
    const [noToken] = await Promise.all([page.waitForResponse((r) => r.url() === base.href, { timeout: WAIT_MS }),
                                         page.goto(base.href).catch(() => null)]);
    // The service refuses the page itself without the token; a page already open (or served
    // from elsewhere) must then say so. The same HTML, fetched with the token, stands in for it.
    const html = await (await fetch(base.href, { headers: { Authorization: `Bearer ${token}` } })).text();
    await page.route(base.href, (route) => route.fulfill({ status: 200, contentType: "text/html", body: html }));
    await page.goto(base.href);
    await until(page, () => window.thermocomp.state === "unauthorised");
    await page.locator("#offline", { hasText: "Not authorised" }).waitFor({ state: "visible", timeout: WAIT_MS });
    emit("no_token", { document_status: noToken.status(), ...(await look(page)), errors });
    await page.unroute(base.href);
    const withToken = new URL(base.href);
    withToken.searchParams.set("token", token);
    const resp = await page.goto(withToken.href);
    await plotted(page);
    emit("token", { document_status: resp.status(), ...(await look(page)), errors });
    await until(page, () => window.thermocomp.state === "unreachable");
    await page.locator("#offline", { hasText: "Service not reachable" }).waitFor({ state: "visible", timeout: WAIT_MS });
    await page.screenshot({ path: shot });
    emit("unreachable", { ...(await look(page)), screenshot: shot, errors });
    // back: a new pid, so the page drops the old series and fetches the new history
    await until(page, () => window.thermocomp.state === "live" && window.thermocomp.plotted > 0);
    emit("recovered", { ...(await look(page)), errors });
  } else if (scenario === "not_writing") {
    const resp = await page.goto(url);
    // past "starting" (no cycle yet, also not writing): the first cycle has met the closed port
    await until(page, () => window.thermocomp.spindle_state === "not writing"
                && (window.thermocomp.spindle_reason ?? "").startsWith("link down"));
    await page.screenshot({ path: shot });
    const bar = await page.evaluate(() => {
      const el = document.getElementById("state"), svc = document.getElementById("svc");
      return { state_bar: el.innerText, state_border: getComputedStyle(el).borderLeftColor,
               header: svc.innerText, header_color: getComputedStyle(svc).color };
    });
    emit("not_writing", { document_status: resp.status(), ...(await look(page)), ...bar, screenshot: shot, errors });
  } else if (scenario === "stopped") {
    const bar = () => page.evaluate(() => ({ state_bar: document.getElementById("state").innerText,
                                             state_class: document.getElementById("state").className }));
    const resp = await page.goto(url);
    await until(page, () => window.thermocomp.state === "live" && window.thermocomp.spindle_state === "compensating");
    emit("live", { document_status: resp.status(), ...(await look(page)), ...(await bar()), errors });
    await until(page, () => window.thermocomp.spindle_state === "stopped");
    emit("stopped", { ...(await look(page)), ...(await bar()), errors });
    await until(page, () => window.thermocomp.state === "unreachable");
    await page.screenshot({ path: shot });
    emit("gone", { ...(await look(page)), ...(await bar()), screenshot: shot, errors });
  } else {
    throw new Error(`unknown scenario ${scenario}`);
  }
} catch (e) {
  failed = true;
  emit("error", { error: String(e && e.stack ? e.stack : e).slice(0, 2000) });
} finally {
  await browser.close();
}
process.exit(failed ? 1 : 0);
