// stg_node web page client: the WebSocket to the web node, its clock, and canvases that show the
// newest frame of a stream and measure how old it is when drawn (docs/NODES.md, "web").
// Plain ES module: no build step, no third-party code.
"use strict";

const PING_EVERY_MS = 1000;
const FIRST_PINGS = 5; // quick pings at start: a clock offset before the first frames
const CLOCK_SAMPLES = 30; // the offset is that of the quickest round trip among the last these
const AGES_KEPT = 2000; // frame ages kept for the percentiles (about a minute at 30 fps)
const REPORT_EVERY_MS = 2000;

function epochMs() {
  return performance.timeOrigin + performance.now();
}

function percentile(sorted, q) {
  if (!sorted.length) return null;
  const i = Math.min(sorted.length - 1, Math.max(0, Math.round(q * (sorted.length - 1))));
  return sorted[i];
}

// The connection to the web node: subscribes to streams, keeps the server's clock, reconnects.
export class Live {
  constructor(streams, handlers) {
    this.streams = streams;
    this.handlers = handlers;
    this.offsetMs = 0; // server clock - this clock
    this.bestRttMs = Infinity;
    this.clockSamples = []; // [rtt, offset] of the last pings
    this.pings = 0;
    this.connected = false;
    this.reports = []; // functions returning {name: stats} for the server's /stats.json
    this.onstate = null;
    this.connect();
    setInterval(() => this.report(), REPORT_EVERY_MS);
  }

  connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const token = new URLSearchParams(location.search).get("token");
    const query = token ? `?token=${encodeURIComponent(token)}` : "";
    const ws = new WebSocket(`${proto}//${location.host}/ws${query}`);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      this.connected = true;
      this.bestRttMs = Infinity;
      this.clockSamples = [];
      this.pings = 0;
      ws.send(JSON.stringify({ op: "subscribe", streams: this.streams }));
      this.ping();
      if (this.onstate) this.onstate("connected");
    };
    ws.onclose = () => {
      this.connected = false;
      if (this.onstate) this.onstate("disconnected");
      setTimeout(() => this.connect(), 1000);
    };
    ws.onmessage = (event) => this.receive(event.data);
  }

  ping() {
    if (!this.connected) return;
    this.ws.send(JSON.stringify({ op: "ping", t: epochMs() }));
    this.pings += 1;
    setTimeout(() => this.ping(), this.pings < FIRST_PINGS ? 200 : PING_EVERY_MS);
  }

  // NTP-style: the server's clock is taken as read halfway through the round trip, which is off
  // by at most half the trip: the quickest trip among the last CLOCK_SAMPLES wins (a busy machine
  // delays some), and old samples leave the window, so a drifting clock is followed.
  pong(msg) {
    const now = epochMs();
    const rtt = now - msg.t;
    this.clockSamples.push([rtt, msg.server_ns / 1e6 - (msg.t + now) / 2]);
    if (this.clockSamples.length > CLOCK_SAMPLES) this.clockSamples.shift();
    const best = this.clockSamples.reduce((a, b) => (b[0] < a[0] ? b : a));
    this.bestRttMs = best[0];
    this.offsetMs = best[1];
  }

  serverNowMs() {
    return epochMs() + this.offsetMs;
  }

  receive(data) {
    if (typeof data === "string") {
      const msg = JSON.parse(data);
      if (msg.stream === "pong") return this.pong(msg);
      const handler = this.handlers[msg.stream];
      if (handler) handler(msg, null);
      return;
    }
    const view = new DataView(data);
    const headLength = view.getUint32(0);
    const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(data, 4, headLength)));
    const handler = this.handlers[meta.stream];
    if (handler) handler(meta, new Uint8Array(data, 4 + headLength));
  }

  report() {
    if (!this.connected) return;
    const report = { page: location.pathname, clock_rtt_ms: this.bestRttMs };
    for (const get of this.reports) Object.assign(report, get());
    this.ws.send(JSON.stringify({ op: "report", report }));
  }
}

// Shows the newest image of a stream in a canvas: decoded off the main thread
// (createImageBitmap), drawn in the next animation frame; a frame overtaken before it was drawn
// is skipped (counted). Frame age = the server's clock when drawn - the image's publish stamp.
export class FrameView {
  constructor(live, canvas, { fit = "contain", type = "image/jpeg", overlay = null } = {}) {
    this.live = live;
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.fit = fit;
    this.type = type;
    this.overlay = overlay; // function(ctx, box) drawing over the frame
    this.pending = null;
    this.current = null;
    this.lastStamp = 0;
    this.shown = 0;
    this.skipped = 0;
    this.ages = [];
    this.shownTimes = [];
    this.lastAgeMs = null;
    this.drawScheduled = false;
  }

  push(meta, bytes) {
    createImageBitmap(new Blob([bytes], { type: this.type })).then((bitmap) => {
      if (meta.stamp_ns < this.lastStamp) {
        bitmap.close(); // decoded after a newer one
        return;
      }
      if (this.pending) {
        this.pending.bitmap.close();
        this.skipped += 1;
      }
      this.pending = { bitmap, meta };
      this.lastStamp = meta.stamp_ns;
      this.schedule();
    });
  }

  schedule() {
    if (!this.drawScheduled) {
      this.drawScheduled = true;
      requestAnimationFrame(() => this.draw());
    }
  }

  box(width, height) {
    const cw = this.canvas.width, ch = this.canvas.height;
    if (this.fit === "fill") return { x: 0, y: 0, w: cw, h: ch, scale: cw / width };
    const scale = Math.min(cw / width, ch / height);
    const w = width * scale, h = height * scale;
    return { x: (cw - w) / 2, y: (ch - h) / 2, w, h, scale };
  }

  draw() {
    this.drawScheduled = false;
    const fresh = this.pending;
    if (fresh) {
      if (this.current) this.current.bitmap.close();
      this.current = fresh;
      this.pending = null;
    }
    if (!this.current) return;
    const { bitmap, meta } = this.current;
    const ctx = this.ctx;
    ctx.fillStyle = "#000";
    ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    const box = this.box(bitmap.width, bitmap.height);
    ctx.drawImage(bitmap, box.x, box.y, box.w, box.h);
    if (this.overlay) this.overlay(ctx, box, meta);
    if (fresh && meta.stamp_ns) {
      const age = this.live.serverNowMs() - meta.stamp_ns / 1e6;
      this.lastAgeMs = age;
      this.ages.push(age);
      if (this.ages.length > AGES_KEPT) this.ages.shift();
      this.shown += 1;
      this.shownTimes.push(performance.now());
      if (this.shownTimes.length > 60) this.shownTimes.shift();
    }
  }

  redraw() {
    this.schedule();
  }

  // Start the counts and ages afresh (a benchmark's measuring window).
  reset() {
    this.shown = 0;
    this.skipped = 0;
    this.ages = [];
    this.shownTimes = [];
  }

  stats() {
    const sorted = [...this.ages].sort((a, b) => a - b);
    const times = this.shownTimes;
    const span = times.length > 1 ? (times[times.length - 1] - times[0]) / 1000 : 0;
    return {
      shown: this.shown,
      skipped: this.skipped,
      age_last_ms: this.lastAgeMs,
      age_p50_ms: percentile(sorted, 0.5),
      age_p95_ms: percentile(sorted, 0.95),
      fps: span > 0 ? (times.length - 1) / span : 0,
      width: this.current ? this.current.bitmap.width : 0,
      height: this.current ? this.current.bitmap.height : 0,
    };
  }
}

// Keeps a canvas's backing store at its on-screen size (sharp on any screen) and redraws.
export function fitCanvas(canvas, view) {
  const resize = () => {
    const ratio = window.devicePixelRatio || 1;
    const rect = canvas.getBoundingClientRect();
    canvas.width = Math.max(1, Math.round(rect.width * ratio));
    canvas.height = Math.max(1, Math.round(rect.height * ratio));
    view.redraw();
  };
  window.addEventListener("resize", resize);
  resize();
}

export function fmt(value, digits = 1) {
  if (value === null || value === undefined || Number.isNaN(value)) return "–";
  return Number(value).toFixed(digits);
}

export function text(el, value) {
  if (el.textContent !== value) el.textContent = value;
}
