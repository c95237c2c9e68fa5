// Survey: upload a video of the room (upload progress), then follow the job: stage,
// progress and time left, live; cancel; the result with its warnings against the cards
// they name.

import { api, postForm } from "./api.js";
import { fixed, h, notify } from "./dom.js";

const POLL_MS = 500;
/** Where the page remembers the environment's last survey job, to follow it or show it again. */
const jobKey = (environmentId) => `fidotrack.surveyJob.${environmentId}`;

function duration(seconds) {
  if (!Number.isFinite(seconds) || seconds < 0) return "–";
  const m = Math.floor(seconds / 60);
  const s = Math.round(seconds % 60);
  return m > 0 ? `${m} min ${s} s` : `${s} s`;
}

/** Time left from the progress made since the job started (linear in progress). */
function timeLeft(job) {
  if (!job.started_at || job.progress < 0.03 || job.progress >= 1) return NaN;
  const elapsed = (Date.now() - Date.parse(job.started_at)) / 1000;
  return elapsed * (1 - job.progress) / job.progress;
}

/** The survey's warnings, each with chips for the cards it names (they open the map on that card). */
export function warningList(environmentId, result) {
  const typed = result.card_warnings || [];
  const typedText = new Set(typed.map((w) => w.message));
  const items = [
    ...typed.map((w) => h("li", { "data-kind": w.kind },
      w.target_ids.map((id) => h("a", { class: "chip", href: `#/environments/${environmentId}/map/${id}` }, `card ${id}`)),
      " ", w.message)),
    ...(result.warnings || []).filter((text) => !typedText.has(text)).map((text) => h("li", {}, text)),
  ];
  return items.length ? h("ul", { class: "warnings" }, items) : h("p", { class: "ok" }, "No warnings.");
}

export async function surveyPage(view, environmentId) {
  const environment = await api("GET", `/environments/${environmentId}`);
  const state = { environmentId, upload: null, job: null };
  window.fidotrack.survey = state;

  const file = h("input", { type: "file", name: "video", accept: "video/*,.mp4,.mov,.avi", required: true });
  const size = h("input", { type: "number", min: 10, step: "any", value: environment.marker_size_m * 1000 });
  const maxFrames = h("input", { type: "number", min: 2, placeholder: "default", id: "survey-frames" });
  const features = h("input", { type: "checkbox", id: "survey-features", checked: true });
  const readout = h("input", { type: "number", min: 0.1, max: 100, step: 0.1, placeholder: "none",
                               id: "survey-readout" });
  const uploadBar = h("progress", { max: 1, value: 0 });
  const uploadText = h("span", { class: "muted" }, "");
  const jobBar = h("progress", { id: "job-progress", max: 1, value: 0 });
  const jobText = h("div", { id: "job-stage" }, "");
  const cancel = h("button", { class: "secondary", disabled: true }, "Cancel");
  const outcome = h("div", { id: "survey-result" });
  const start = h("button", { type: "submit" }, "Upload and survey");
  let timer = null;
  let stopped = false;

  function showResult(job) {
    outcome.replaceChildren();
    if (job.status === "succeeded") {
      const r = job.result;
      outcome.append(
        h("h2", {}, "Result"),
        h("p", {}, `${r.n_targets} cards mapped from ${r.n_registered} of ${r.n_frames} frames; `,
          `reprojection RMS ${fixed(r.rms_px, 2)} px; focal length ${fixed(r.focal_px, 1)} px. `,
          h("a", { href: `#/environments/${environmentId}/map` }, "Open the map")),
        h("h2", {}, "Warnings"), warningList(environmentId, r));
    } else if (job.status === "failed") {
      outcome.append(h("p", { class: "bad" }, `The survey failed: ${job.error}`));
    } else if (job.status === "cancelled") {
      outcome.append(h("p", { class: "muted" }, "The survey was cancelled; the previous map (if any) is kept."));
    }
  }

  async function follow(jobId) {
    sessionStorage.setItem(jobKey(environmentId), jobId);
    cancel.disabled = false;
    cancel.onclick = async () => {
      cancel.disabled = true;  // the next poll shows the job cancelled
      try { await api("DELETE", `/jobs/${jobId}`); } catch (error) { notify(error.message); cancel.disabled = false; }
    };
    while (!stopped) {
      let job;
      try {
        job = await api("GET", `/jobs/${jobId}`);
      } catch (error) {
        notify(error.message);
        if (error.status === 404) { sessionStorage.removeItem(jobKey(environmentId)); return; }
        await new Promise((resolve) => { timer = setTimeout(resolve, 2000); });
        continue;
      }
      state.job = job;
      jobBar.value = job.progress;
      jobText.textContent = `${job.status}: ${job.stage}${job.message ? ` (${job.message})` : ""} · `
        + `${Math.round(job.progress * 100)} % · about ${duration(timeLeft(job))} left`;
      if (["succeeded", "failed", "cancelled"].includes(job.status)) {
        jobText.textContent = `${job.status} · ${job.stage}`;
        cancel.disabled = true;
        start.disabled = false;
        showResult(job);  // (the job stays remembered: coming back to the page shows the last survey)
        return;
      }
      await new Promise((resolve) => { timer = setTimeout(resolve, POLL_MS); });
    }
  }

  const form = h("form", { class: "inline", onsubmit: async (event) => {
    event.preventDefault();
    if (!file.files.length) return;
    const data = new FormData();
    data.append("video", file.files[0]);
    data.append("marker_size_m", String(Number(size.value) / 1000));
    if (maxFrames.value) data.append("max_frames", maxFrames.value);
    data.append("feature_tracks", features.checked ? "true" : "false");
    if (readout.value) data.append("readout_ms", readout.value);
    start.disabled = true;
    outcome.replaceChildren();
    const began = performance.now();
    state.upload = { sent: 0, total: file.files[0].size, done: false };
    try {
      const job = await postForm(`/environments/${environmentId}/survey`, data, (sent, total) => {
        state.upload.sent = sent;
        uploadBar.value = total ? sent / total : 0;
        const rate = sent / Math.max(0.001, (performance.now() - began) / 1000);
        uploadText.textContent = `${fixed(sent / 1e6, 1)} of ${fixed(total / 1e6, 1)} MB · ${fixed(rate / 1e6, 1)} MB/s`;
      });
      state.upload.done = true;
      uploadBar.value = 1;
      await follow(job.id);
    } catch (error) {
      notify(error.message);
      start.disabled = false;
    }
  } },
    h("label", {}, "Video of the room", file),
    h("label", {}, "Printed card side (mm)", size),
    h("label", {}, "Frames to use", maxFrames),
    h("label", { title: "Unticked: the cards alone" }, h("span", {}, features, " track the walls' texture too"), ""),
    h("label", { title: "A phone's rolling shutter, first row to last (10-30 ms); empty: a global shutter" },
      "Readout (ms)", readout),
    start);

  view.append(
    h("h1", {}, `Survey: ${environment.name}`),
    h("p", { class: "muted" }, "Film every card from several places, walking round the room; ",
      "see the filming guide in the docs. A new map replaces the old one only when the survey succeeds."),
    form,
    h("div", { class: "panel" }, h("div", {}, "Upload ", uploadText), uploadBar,
      h("div", { style: "margin-top:.6rem" }, "Survey ", jobText), jobBar, h("div", { style: "margin-top:.4rem" }, cancel)),
    outcome);

  const pending = sessionStorage.getItem(jobKey(environmentId));
  if (pending) { start.disabled = true; follow(pending); }
  return () => { stopped = true; clearTimeout(timer); };
}
