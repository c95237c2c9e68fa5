// Detection check: drop an image, see what the detector found: every disc candidate that
// passed the classifier, and the identified targets with their ids.

import { api, postImage } from "./api.js";
import { drawTarget, fixed, h, notify } from "./dom.js";

function draw(canvas, image, result) {
  canvas.width = result.width;
  canvas.height = result.height;
  const g = canvas.getContext("2d");
  g.drawImage(image, 0, 0);
  const unit = Math.max(1, result.width / 800);
  g.lineWidth = 1.5 * unit;
  g.strokeStyle = "#ffb300";
  for (const [u, v, r] of result.candidates || []) {
    g.beginPath(); g.arc(u, v, Math.max(3 * unit, r || 0), 0, 2 * Math.PI); g.stroke();
  }
  g.lineWidth = 3 * unit;
  for (const target of result.targets) drawTarget(g, target, "#00e676", 18 * unit);
}

export async function detectPage(view) {
  const classifiers = await api("GET", "/classifiers");
  const state = { result: null };
  window.fidotrack.detect = state;
  const classifier = h("select", { id: "detect-classifier" },
    classifiers.map((c) => h("option", { value: c.id, selected: c.is_default }, `${c.name} (#${c.id})`)));
  const file = h("input", { type: "file", accept: "image/jpeg,image/png", id: "detect-file" });
  const drop = h("div", { class: "drop", id: "drop" }, "Drop a JPEG or PNG here, or choose one: ", file);
  const canvas = h("canvas", { class: "picture", id: "detect-canvas" });
  const summary = h("div", { id: "detect-summary" });

  async function check(blob) {
    notify("");
    try {
      const image = await createImageBitmap(blob);
      const result = await postImage(`/detect?candidates=true&classifier_id=${classifier.value}`, blob);
      state.result = result;
      draw(canvas, image, result);
      summary.replaceChildren(h("p", {},
        `${result.targets.length} targets (ids ${result.targets.map((t) => t.id).sort((a, b) => a - b).join(", ") || "none"}), `,
        `${(result.candidates || []).length} disc candidates, in ${fixed(result.timing_ms.total, 1)} ms on the server. `,
        h("span", { class: "muted" }, "Green: identified targets; amber: discs the classifier accepted.")));
    } catch (error) { notify(error.message); }
  }

  file.addEventListener("change", () => file.files.length && check(file.files[0]));
  drop.addEventListener("dragover", (event) => { event.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (event) => {
    event.preventDefault();
    drop.classList.remove("over");
    if (event.dataTransfer.files.length) check(event.dataTransfer.files[0]);
  });
  view.append(h("h1", {}, "Detection check"),
    h("p", { class: "muted" }, "What the detector sees in one picture of your cards: check print, light and distance before filming a survey."),
    h("label", {}, "Classifier", classifier), drop, summary, h("div", { class: "stage" }, canvas));
}
