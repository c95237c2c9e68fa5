// Live tracking from the browser's camera: frames resized and JPEG-encoded in the page,
// streamed to /track in lock-step (the next frame leaves when the previous reply is in,
// so latency cannot build up), the detections drawn over the video and the pose shown
// in the 3D map with its uncertainty; fps, latency and dropped frames measured here.

import { trackUrl } from "./api.js";
import { drawTarget, fixed, h, notify, quantile } from "./dom.js";
import { loadMap } from "./map.js";
import { MapView } from "./scene.js";

/** Replies kept for the statistics (and for anyone reading window.fidotrack.track). */
const KEPT_REPLIES = 5000;
const STATS_WINDOW = 120;

/** Draw a reply's targets (their discs, outline and id) on the overlay, in frame pixels. */
function drawTargets(overlay, reply) {
  overlay.width = reply.width;
  overlay.height = reply.height;
  const g = overlay.getContext("2d");
  g.clearRect(0, 0, overlay.width, overlay.height);
  const unit = Math.max(1, reply.width / 640);
  g.lineWidth = 2 * unit;
  for (const target of reply.targets) {
    const used = reply.pose && !reply.pose.rejected_targets.includes(target.id);
    drawTarget(g, target, used ? "#00e676" : "#ffb300", 16 * unit);
    for (const [u, v] of target.discs) { g.beginPath(); g.arc(u, v, 5 * unit, 0, 2 * Math.PI); g.stroke(); }
  }
}

export async function trackPage(view, environmentId) {
  const loaded = await loadMap(environmentId);
  const state = { environmentId, running: false, sent: 0, replies: [], errors: [], encodeMs: [], hello: null,
                  mapChanges: 0 };
  window.fidotrack.track = state;

  const video = h("video", { autoplay: true, muted: true, playsinline: true, id: "camera" });
  const overlay = h("canvas", { class: "overlay", id: "overlay" });
  const widthSelect = h("select", { id: "frame-width" },
    [["native", "camera's size"], ["1280", "1280 px wide"], ["640", "640 px wide"], ["320", "320 px wide"]]
      .map(([value, text]) => h("option", { value, selected: value === "640" }, text)));
  const quality = h("input", { id: "jpeg-quality", type: "number", min: 0.3, max: 1, step: 0.05, value: 0.85 });
  const deviceSelect = h("select", { id: "camera-device" }, h("option", { value: "" }, "default camera"));
  const startButton = h("button", { id: "start" }, "Start");
  const stats = h("div", { class: "stats", id: "track-stats" });
  const poseText = h("pre", { id: "pose", class: "panel" }, "No pose yet.");
  const container = h("div", { class: "viewer", id: "track-view" });
  view.append(
    h("h1", {}, `Track: ${loaded.environment.name}`),
    h("div", { class: "inline" },
      h("form", { class: "inline", onsubmit: (event) => { event.preventDefault(); state.running ? stop() : start(); } },
        h("label", {}, "Camera", deviceSelect), h("label", {}, "Frames sent", widthSelect),
        h("label", {}, "JPEG quality", quality), startButton)),
    stats,
    h("div", { class: "grid" }, h("div", { class: "stage" }, video, overlay), h("div", {}, container, poseText)));
  // The 3D view follows the pose at 10 frames a second: enough to watch, and it leaves
  // the page's time to the frames (a browser without a GPU draws it in software).
  const viewer = new MapView(container, { maxFps: 10 });
  viewer.setMap(loaded.map, loaded.discsUv);

  const canvas = document.createElement("canvas");
  let stream = null;
  let socket = null;

  function showStats() {
    const recent = state.replies.slice(-STATS_WINDOW);
    const span = recent.length > 1 ? (recent.at(-1).receivedAt - recent[0].receivedAt) / 1000 : 0;
    const posed = recent.filter((r) => r.pose).length;
    const items = [
      ["fps", fixed(span > 0 ? (recent.length - 1) / span : NaN, 1)],
      ["latency p50", `${fixed(quantile(recent.map((r) => r.latencyMs), 0.5), 0)} ms`],
      ["latency p99", `${fixed(quantile(recent.map((r) => r.latencyMs), 0.99), 0)} ms`],
      ["server p50", `${fixed(quantile(recent.map((r) => r.serverMs), 0.5), 1)} ms`],
      ["encode p50", `${fixed(quantile(recent.map((r) => r.encodeMs), 0.5), 1)} ms`],
      ["with pose", `${fixed(recent.length ? (100 * posed) / recent.length : NaN, 0)} %`],
      ["dropped", String(state.replies.reduce((n, r) => n + r.dropped, 0))],
      ["frames", String(state.sent)],
    ];
    stats.replaceChildren(...items.map(([name, value]) => h("div", {}, h("span", { class: "muted" }, name), h("b", {}, value))));
  }

  function frameSize() {
    const w = video.videoWidth, hgt = video.videoHeight;
    const target = widthSelect.value === "native" ? w : Math.min(w, Number(widthSelect.value));
    return [target, Math.round((hgt * target) / w)];
  }

  /** Encode the video's current picture; resolves to [bytes, draw + encode ms, when the draw began]. */
  async function capture() {
    const began = performance.now();
    const [w, hgt] = frameSize();
    if (canvas.width !== w || canvas.height !== hgt) { canvas.width = w; canvas.height = hgt; }
    canvas.getContext("2d").drawImage(video, 0, 0, w, hgt);
    const blob = await new Promise((resolve) => canvas.toBlob(resolve, "image/jpeg", Number(quality.value)));
    const bytes = await blob.arrayBuffer();
    return [bytes, performance.now() - began, began];
  }

  let pending = null;  // the frame awaiting its reply: {seq, began, encodeMs}
  let greeted = false;  // this connection's first hello came

  /** A hello after the first: the environment's map (or classifier) changed on the server
   * and the next replies are posed against the new one; the 3D view shows it too. */
  async function onMapChange(hello) {
    state.mapChanges += 1;
    notify(hello.reason === "map_changed" ? "The map changed: tracking against the new map."
      : "The classifier changed: tracking with the new one.");
    if (hello.reason !== "map_changed") return;
    try {
      const fresh = await loadMap(environmentId);
      viewer.setMap(fresh.map, fresh.discsUv);
    } catch (error) {
      notify(`The map changed but could not be loaded: ${error.message}`);
    }
  }

  async function sendNext() {
    if (!state.running || socket.readyState !== WebSocket.OPEN) return;
    if (video.readyState < 2) { setTimeout(sendNext, 30); return; }
    const [bytes, encodeMs, began] = await capture();
    if (!state.running) return;
    pending = { seq: state.sent, began, encodeMs };
    state.sent += 1;
    socket.send(bytes);
  }

  function onMessage(event) {
    const message = JSON.parse(event.data);
    if (message.type === "hello") {
      state.hello = message;
      // The first starts the lock-step; a later one comes between two replies, while a
      // frame is out (or being captured): its reply goes on with the lock-step.
      if (!greeted) { greeted = true; sendNext(); } else { onMapChange(message); }
      return;
    }
    if (message.type === "frame") {
      const now = performance.now();
      const record = {
        seq: message.seq, receivedAt: now, latencyMs: pending ? now - pending.began : NaN,
        encodeMs: pending ? pending.encodeMs : NaN, serverMs: message.timing_ms.total ?? NaN, dropped: message.dropped,
        width: message.width, height: message.height, targets: message.targets.map((t) => t.id),
        pose: message.pose ? { R: message.pose.R, t: message.pose.t, position: message.pose.position,
                               covariance_position: message.pose.covariance_position } : null,
        poseError: message.pose_error,
      };
      state.replies.push(record);
      if (state.replies.length > KEPT_REPLIES) state.replies.shift();
      drawTargets(overlay, message);
      viewer.setCamera(message.pose);
      poseText.textContent = message.pose
        ? `position (m): ${message.pose.position.map((x) => fixed(x, 3)).join(", ")}\n`
          + `1-sigma (mm): ${message.pose.covariance_position.map((row, i) => fixed(Math.sqrt(row[i]) * 1000, 1)).join(", ")}\n`
          + `targets: ${message.pose.n_targets} · reprojection ${fixed(message.pose.reprojection_rms_px, 2)} px`
        : `No pose: ${message.pose_error || "no target seen"}`;
      showStats();
      pending = null;
      sendNext();
      return;
    }
    if (message.type === "error") {
      state.errors.push(message);
      if (message.code === "rate_limited") return;
      notify(`${message.code}: ${message.message}`);
      if (message.seq !== null && message.seq !== undefined && pending && message.seq === pending.seq) {
        pending = null;
        sendNext();  // a refused frame: go on with the next
      }
    }
  }

  async function start() {
    notify("");
    try {
      const constraints = { video: deviceSelect.value ? { deviceId: { exact: deviceSelect.value } }
        : { facingMode: "environment", width: { ideal: 1280 }, height: { ideal: 720 } }, audio: false };
      stream = await navigator.mediaDevices.getUserMedia(constraints);
    } catch (error) {
      notify(`The camera is not available (${error.name}): a page served over plain http can use it only on `
        + "localhost; serve fidotrack over https to track from a phone (see the docs).");
      return;
    }
    video.srcObject = stream;
    await video.play().catch(() => {});
    if (deviceSelect.options.length === 1) {
      for (const device of await navigator.mediaDevices.enumerateDevices()) {
        if (device.kind === "videoinput") deviceSelect.append(h("option", { value: device.deviceId }, device.label || device.deviceId));
      }
    }
    greeted = false;
    pending = null;
    socket = new WebSocket(trackUrl(environmentId));
    socket.binaryType = "arraybuffer";
    socket.onmessage = onMessage;
    socket.onclose = (event) => {
      if (state.running && event.code !== 1000) notify(`The tracking connection closed (${event.code}${event.reason ? `: ${event.reason}` : ""}).`);
      stop();
    };
    state.running = true;
    startButton.textContent = "Stop";
  }

  function stop() {
    state.running = false;
    startButton.textContent = "Start";
    if (socket && socket.readyState <= WebSocket.OPEN) socket.close(1000);
    if (stream) for (const track of stream.getTracks()) track.stop();
    stream = null;
  }

  showStats();
  return () => { stop(); viewer.dispose(); };
}
