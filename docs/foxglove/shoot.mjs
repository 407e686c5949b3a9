// Opens a page in Debian's Chromium (headless, software GL), waits, and saves a
// screenshot; the page's errors go to stderr. Usage: node shoot.mjs URL OUT.png SECONDS
import puppeteer from "puppeteer-core";

const [url, out, seconds] = process.argv.slice(2);
const browser = await puppeteer.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
  defaultViewport: { width: 1920, height: 1080 },
});
try {
  const page = await browser.newPage();
  page.on("console", (m) => {
    if (m.type() === "error") console.error(`[page] ${m.text()}`);
  });
  page.on("pageerror", (e) => console.error(`[page error] ${e.message}`));
  await page.goto(url, { waitUntil: "load" });
  await new Promise((r) => setTimeout(r, Number(seconds) * 1000));
  await page.screenshot({ path: out });
} finally {
  await browser.close();
}
