// /avatar: the live avatar, full window (a robot's screen). ?stats=1 shows the frame age.
import { FrameView, Live, fitCanvas, fmt, text } from "/static/stg.js";

const canvas = document.getElementById("avatar");
const stats = document.getElementById("stats");
const waiting = document.getElementById("waiting");
const params = new URLSearchParams(location.search);
if (params.get("stats")) stats.classList.remove("hidden");

let view = null;
const live = new Live(["avatar"], {
  avatar: (meta, bytes) => {
    view.push(meta, bytes);
    waiting.classList.add("hidden");
  },
});
view = new FrameView(live, canvas);
fitCanvas(canvas, view);
live.reports.push(() => ({ avatar: view.stats() }));
window.stgStats = {
  get avatar() { return view.stats(); },
  get clockRttMs() { return live.bestRttMs; },
  reset: () => view.reset(),
};

setInterval(() => {
  if (stats.classList.contains("hidden")) return;
  const s = view.stats();
  text(stats, `frame age ${fmt(s.age_last_ms, 0)} ms (p50 ${fmt(s.age_p50_ms, 0)}, p95 ${fmt(s.age_p95_ms, 0)}) · ${fmt(s.fps, 1)} fps`);
}, 500);
