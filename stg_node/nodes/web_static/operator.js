// /: the operator's page. The avatar; the camera with the person mask and the skeleton over it;
// every node's health and rates; the trainer's figures; the frame age of every page.
import { FrameView, Live, fitCanvas, fmt, text } from "/static/stg.js";

const $ = (id) => document.getElementById(id);
const showMask = $("show-mask");
const showSkeleton = $("show-skeleton");
// Masks and skeletons by the seq of the camera frame they belong to: a frame shows its own
// (the pose of a frame arrives after it, and with several cameras consecutive frames differ).
const KEPT = 16;
const masks = new Map(); // frame seq -> ImageBitmap
const skeletons = new Map(); // frame seq -> skeleton stream message
let avatarView = null;
let cameraView = null;

const token = new URLSearchParams(location.search).get("token");
if (token) $("screen-link").href = `/avatar?token=${encodeURIComponent(token)}`;

function keep(map, key, value, release) {
  map.set(key, value);
  while (map.size > KEPT) {
    const [oldest, old] = map.entries().next().value;
    if (release) release(old);
    map.delete(oldest);
  }
}

function showing(seq) {
  return cameraView.current && cameraView.current.meta.seq === seq;
}

function drawOverlay(ctx, box, meta) {
  const scaleX = box.w / meta.width, scaleY = box.h / meta.height;
  const mask = masks.get(meta.seq);
  if (showMask.checked && mask) {
    ctx.drawImage(mask, box.x, box.y, box.w, box.h);
  }
  const skeleton = skeletons.get(meta.seq);
  if (showSkeleton.checked && skeleton && skeleton.width === meta.width) {
    const pts = skeleton.points;
    ctx.lineWidth = Math.max(2, box.w / 200);
    ctx.strokeStyle = "#ff8c1a";
    ctx.beginPath();
    skeleton.parents.forEach((parent, child) => {
      if (parent < 0 || !pts[parent] || !pts[child]) return;
      ctx.moveTo(box.x + pts[parent][0] * scaleX, box.y + pts[parent][1] * scaleY);
      ctx.lineTo(box.x + pts[child][0] * scaleX, box.y + pts[child][1] * scaleY);
    });
    ctx.stroke();
    ctx.fillStyle = "#ffffff";
    for (const p of pts) {
      if (!p) continue;
      ctx.beginPath();
      ctx.arc(box.x + p[0] * scaleX, box.y + p[1] * scaleY, Math.max(2, box.w / 160), 0, 2 * Math.PI);
      ctx.fill();
    }
  }
}

const live = new Live(["avatar", "camera", "mask", "skeleton", "status"], {
  avatar: (meta, bytes) => avatarView.push(meta, bytes),
  camera: (meta, bytes) => cameraView.push(meta, bytes),
  mask: (meta, bytes) => {
    createImageBitmap(new Blob([bytes], { type: "image/png" })).then((bitmap) => {
      keep(masks, meta.seq, bitmap, (old) => old.close());
      if (showing(meta.seq)) cameraView.redraw();
    });
  },
  skeleton: (meta) => {
    keep(skeletons, meta.frame_seq, meta);
    if (showing(meta.frame_seq)) cameraView.redraw();
  },
  status: (meta) => showStatus(meta),
});
avatarView = new FrameView(live, $("avatar"));
cameraView = new FrameView(live, $("camera"), { overlay: drawOverlay });
fitCanvas($("avatar"), avatarView);
fitCanvas($("camera"), cameraView);
showMask.addEventListener("change", () => cameraView.redraw());
showSkeleton.addEventListener("change", () => cameraView.redraw());
live.reports.push(() => ({ avatar: avatarView.stats(), camera: cameraView.stats() }));
live.onstate = (state) => {
  const conn = $("conn");
  text(conn, state === "connected" ? "live" : "reconnecting…");
  conn.classList.toggle("up", state === "connected");
};
window.stgStats = {
  get avatar() { return avatarView.stats(); },
  get camera() { return cameraView.stats(); },
  get clockRttMs() { return live.bestRttMs; },
  status: null,
};

function cell(row, value, className) {
  const td = document.createElement("td");
  td.textContent = value;
  if (className) td.className = className;
  row.appendChild(td);
  return td;
}

function pairs(obj, digits) {
  return Object.entries(obj || {})
    .filter(([, v]) => v)
    .map(([k, v]) => `${k} ${digits === undefined ? v : fmt(v, digits)}`)
    .join(", ");
}

function showStatus(status) {
  window.stgStats.status = status;
  const t = status.trainer;
  if (t) {
    text($("f-iteration"), String(t.iteration));
    text($("f-loss"), fmt(t.loss, 4));
    text($("f-psnr"), fmt(t.psnr, 2));
    text($("f-gaussians"), t.num_gaussians.toLocaleString());
    text($("f-motion"), t.active_motion_fraction === null ? "–" : `${fmt(100 * t.active_motion_fraction, 1)} %`);
    text($("f-its"), fmt(t.it_per_s, 1));
  }
  const rows = [];
  for (const [name, n] of Object.entries(status.nodes)) {
    const row = document.createElement("tr");
    cell(row, name);
    const state = n.alive ? n.state : "silent";
    cell(row, state, `state ${state}`);
    cell(row, n.heartbeat_age_s === null ? "–" : `${fmt(n.heartbeat_age_s, 1)} s`, "num");
    cell(row, pairs(n.rates_hz, 1), "small");
    cell(row, pairs(n.drops), "small");
    const errors = cell(row, String(n.errors), "num");
    if (n.errors) {
      errors.classList.add("error");
      errors.title = n.last_error;
    }
    rows.push(row);
  }
  $("nodes").replaceChildren(...rows);
  const pages = [];
  for (const c of status.web.clients) {
    const a = (c.report && c.report.avatar) || {};
    const row = document.createElement("tr");
    cell(row, `${(c.report && c.report.page) || "another client"} (${c.address})`, "small");
    cell(row, String(a.shown ?? "–"), "num");
    cell(row, a.age_p50_ms == null ? "–" : `${fmt(a.age_p50_ms, 0)} ms`, "num");
    cell(row, a.age_p95_ms == null ? "–" : `${fmt(a.age_p95_ms, 0)} ms`, "num");
    cell(row, fmt(a.fps, 1), "num");
    cell(row, String(c.drops), "num");
    pages.push(row);
  }
  $("pages").replaceChildren(...pages);
}

setInterval(() => {
  const a = avatarView.stats();
  text($("avatar-caption"), a.shown
    ? `${a.width}×${a.height} · frame age ${fmt(a.age_last_ms, 0)} ms (p50 ${fmt(a.age_p50_ms, 0)}, p95 ${fmt(a.age_p95_ms, 0)}) · ${fmt(a.fps, 1)} fps`
    : "waiting for avatar/image…");
  const c = cameraView.stats();
  text($("camera-caption"), c.shown
    ? `${c.width}×${c.height} · frame age ${fmt(c.age_last_ms, 0)} ms · ${fmt(c.fps, 1)} fps`
    : "waiting for camera/frame…");
}, 500);
