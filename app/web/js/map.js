// The map viewer: the surveyed cards in 3D with their ids and precision, the survey's
// trajectory, a top-down view, and alignment to the world (an origin card, or known
// points) with its residuals. Changes are conditional on the map shown (If-Match with its
// ETag): a map changed meanwhile is reloaded, not overwritten.

import { api, request } from "./api.js";
import { fixed, h, notify } from "./dom.js";
import { MapView, STD_SCALE_M } from "./scene.js";

/** HTTP status of a write refused because the map changed since the page read it. */
const MAP_CHANGED = 412;

/**
 * A map, its revision (etag) and what the viewer draws with it: the card layout, and the
 * survey's camera path while the map is still in the survey's frame (the job keeps the
 * path in that frame).
 */
export async function loadMap(environmentId) {
  const [environment, read] = await Promise.all([
    api("GET", `/environments/${environmentId}`), request("GET", `/environments/${environmentId}/map`)]);
  const map = read.body;
  const etag = read.headers.get("ETag");
  const firstId = map.targets.length ? map.targets[0].id : 0;
  const layout = await api("GET", `/markers/${firstId}?family=${environment.marker_family}`);
  let trajectory = [];
  if (map.survey_job_id && map.frame === "survey") {
    try {
      const job = await api("GET", `/jobs/${map.survey_job_id}`);
      trajectory = (job.result?.trajectory || []).filter(Boolean).map((pose) => pose.position);
    } catch { /* the job was pruned: the map stands without its trajectory */ }
  }
  return { environment, map, etag, discsUv: layout.discs, trajectory };
}

/** Points for a point alignment, one per line: "target disc x y z" (disc 0-3, metres). */
function parsePoints(text) {
  return text.split("\n").map((line) => line.trim()).filter((line) => line && !line.startsWith("#")).map((line, i) => {
    const fields = line.split(/[\s,;]+/).map(Number);
    if (fields.length !== 5 || fields.some((x) => !Number.isFinite(x))) {
      throw new Error(`line ${i + 1}: expected "target disc x y z", got "${line}"`);
    }
    return { target_id: fields[0], disc: fields[1], world: fields.slice(2) };
  });
}

export async function mapPage(view, environmentId, focusId) {
  let loaded = await loadMap(environmentId);
  const { environment } = loaded;
  let { map, etag } = loaded;
  const container = h("div", { class: "viewer", id: "map-view" });
  const info = h("div", { id: "map-info" });
  const residuals = h("div", { id: "alignment-residuals" });
  view.append(h("h1", {}, `Map: ${environment.name}`), h("div", { class: "grid" }, container, h("div", {}, info)));
  const viewer = new MapView(container);
  let trajectory = loaded.trajectory;  // in the frame of the map shown
  const state = { environmentId, cards: 0, ids: [], frame: map.frame, trajectory: trajectory.length,
                  alignment: null, focused: null, etag, reloads: 0 };
  // Frames the 3D view has drawn: it draws only when something changes.
  Object.defineProperty(state, "framesDrawn", { get: () => viewer.frames, enumerable: true });
  window.fidotrack.map = state;

  function draw() {
    viewer.setMap(map, loaded.discsUv);
    viewer.setTrajectory(trajectory);
    state.trajectory = trajectory.length;
    state.cameraPath = trajectory;
    state.cards = viewer.cards.size;
    state.ids = [...viewer.cards.keys()].sort((a, b) => a - b);
    state.frame = map.frame;
    describe();
    if (focusId !== undefined) {
      state.focused = viewer.focusCard(focusId) ? focusId : null;
      if (state.focused === null) notify(`Card ${focusId} is not in the map: the survey's warnings say why.`);
    }
  }

  const originSelect = h("select", { id: "origin-card" });
  const pointsText = h("textarea", { rows: 5, cols: 34, placeholder: "# target disc x y z (metres)\n3 0 0 0 0\n..." });
  const allowScale = h("input", { type: "checkbox" });
  const force = h("input", { type: "checkbox", id: "force-fit" });

  /** A change of the map, sent only over the map shown (If-Match); its reply's ETag kept. */
  async function change(path, body) {
    const reply = await request("POST", `/environments/${environmentId}${path}`, body, etag ? { "If-Match": etag } : {});
    etag = state.etag = reply.headers.get("ETag");
    return reply.body;
  }

  /** The map as it is now, after a change was refused because another replaced the one shown. */
  async function reload() {
    loaded = await loadMap(environmentId);
    ({ map, etag } = loaded);
    trajectory = loaded.trajectory;
    state.etag = etag;
    state.alignment = null;
    state.reloads += 1;
    draw();
    residuals.replaceChildren(h("p", { class: "muted", id: "map-reloaded" },
      "The map changed meanwhile (another survey, import, alignment or restore): this is the map now. " +
      "Nothing was changed: check it and try again."));
  }

  async function refused(error) {
    if (error.status !== MAP_CHANGED) { notify(error.message); return; }
    notify("The map changed meanwhile, so nothing was changed: reloaded it.");
    try { await reload(); } catch (failed) { notify(failed.message); }
  }

  async function align(spec) {
    try {
      const result = await change("/alignment", spec);
      state.alignment = { scale: result.scale, rms_m: result.rms_m, residuals: result.residuals };
      map = result.map;
      // The camera path moves with the map: x_world = scale R x + t.
      trajectory = trajectory.map((x) => result.R.map((row, i) =>
        result.scale * (row[0] * x[0] + row[1] * x[1] + row[2] * x[2]) + result.t[i]));
      draw();
      residuals.replaceChildren(
        h("p", {}, `Scale ${fixed(result.scale, 4)} · RMS ${fixed(result.rms_m * 1000, 2)} mm`),
        result.residuals.length ? h("table", {}, h("tr", {}, h("th", {}, "card"), h("th", {}, "disc"), h("th", {}, "residual (mm)")),
          result.residuals.map((r) => h("tr", {}, h("td", {}, String(r.target_id)), h("td", {}, String(r.disc)),
                                                h("td", {}, fixed(r.residual_m * 1000, 2))))) : "");
    } catch (error) { await refused(error); }
  }

  async function restore() {
    try {
      map = await change("/map/restore", {});
      state.alignment = null;
      residuals.replaceChildren(h("p", { class: "muted" }, "The previous map is back."));
      // The camera path is known in the survey's frame only.
      trajectory = map.frame === "survey" && map.survey_job_id === loaded.map.survey_job_id ? loaded.trajectory : [];
      draw();
    } catch (error) { await refused(error); }
  }

  function describe() {
    const worst = [...viewer.cards.entries()].filter(([, card]) => Number.isFinite(card.std))
      .sort((a, b) => b[1].std - a[1].std).slice(0, 5);
    originSelect.replaceChildren(...state.ids.map((id) => h("option", { value: id }, `card ${id}`)));
    info.replaceChildren(
      h("div", { class: "panel" },
        h("p", {}, h("b", { id: "card-count" }, String(state.cards)), " cards · frame ", h("b", {}, map.frame),
          map.rms_px ? ` · survey RMS ${fixed(map.rms_px, 2)} px` : "",
          trajectory.length ? ` · ${trajectory.length} survey frames` : ""),
        h("p", { class: "muted" }, `Colour: each card's largest disc standard deviation, green ${STD_SCALE_M[0] * 1000} mm `,
          `to red ${STD_SCALE_M[1] * 1000} mm. Drag to orbit, right-drag to pan, scroll to zoom.`),
        worst.length ? h("p", {}, "Least precise: ", worst.map(([id, card]) => h("a", { class: "chip", onclick: () => viewer.focusCard(id) },
          `${id}: ${fixed(card.std * 1000, 2)} mm`))) : h("p", { class: "muted" }, "The map gives no precision."),
        h("div", {}, h("button", { class: "secondary", onclick: () => viewer.topDown() }, "Top down"), " ",
          h("button", { class: "secondary", onclick: () => viewer.perspective() }, "Perspective"), " ",
          h("a", { href: `#/environments/${environmentId}/track` }, "Track a camera"))),
      h("div", { class: "panel", style: "margin-top:1rem" },
        h("h2", {}, "Align to the world"),
        h("form", { class: "inline", onsubmit: (event) => {
          event.preventDefault();
          align({ origin_target_id: Number(originSelect.value) });
        } }, h("label", {}, "Origin card (its plane becomes z = 0)", originSelect), h("button", {}, "Set origin")),
        h("form", { onsubmit: (event) => {
          event.preventDefault();
          try { align({ points: parsePoints(pointsText.value), allow_scale: allowScale.checked, force: force.checked }); }
          catch (error) { notify(error.message); }
        } }, h("label", {}, "Known disc positions", pointsText),
          h("label", {}, h("span", {}, allowScale, " fit the scale too")),
          h("label", {}, h("span", {}, force, " store it even if refused (residuals over 2 cm, scale off)")),
          h("button", {}, "Fit")),
        residuals,
        h("p", {}, h("button", { class: "secondary", id: "restore-map", onclick: restore }, "Restore the previous map"),
          " ", h("span", { class: "muted" }, "undoes the last change (a survey, an import, an alignment)"))));
  }

  draw();
  return () => viewer.dispose();
}
