// Environments: list them, create one (card size, classifier), print its cards, choose
// its classifier, and go on to its survey, map and live tracking.

import { api, openFile } from "./api.js";
import { fixed, h, notify } from "./dom.js";

/** The sheet of cards to print: ids 0..n-1 at the environment's card size. */
function sheetPath(environment, count) {
  const mm = Math.round(environment.marker_size_m * 1000 * 10) / 10;
  return `/markers/sheet.pdf?ids=0-${count - 1}&size_mm=${mm}&family=${environment.marker_family}`;
}

export async function environmentsPage(view) {
  const [environments, classifiers] = await Promise.all([api("GET", "/environments"), api("GET", "/classifiers")]);
  window.fidotrack.environments = environments;
  const classifierName = new Map(classifiers.map((c) => [c.id, c.name]));

  const classifierSelect = (selected, onchange) => h("select", { onchange },
    h("option", { value: "" }, "default"),
    classifiers.map((c) => h("option", { value: c.id, selected: c.id === selected }, `${c.name} (#${c.id})`)));

  const rows = environments.map((environment) => {
    const sheetCount = h("input", { type: "number", min: 1, max: 200, value: 12, style: "width:4.5rem",
                                      "aria-label": "cards on the sheet" });
    return h("tr", { "data-environment": environment.id },
      h("td", {}, String(environment.id)),
      h("td", {}, environment.name),
      h("td", {}, `${fixed(environment.marker_size_m * 1000, 0)} mm`),
      h("td", {}, environment.has_map ? h("span", { class: "ok" }, "mapped") : h("span", { class: "muted" }, "no map")),
      h("td", {}, classifierSelect(environment.classifier_id, async (event) => {
        const value = event.target.value === "" ? null : Number(event.target.value);
        try {
          await api("PATCH", `/environments/${environment.id}`, { classifier_id: value });
          notify("");
        } catch (error) { notify(error.message); }
      })),
      h("td", { class: "actions" },
        h("a", { href: `#/environments/${environment.id}/survey` }, "Survey"),
        environment.has_map ? h("a", { href: `#/environments/${environment.id}/map` }, "Map") : null,
        environment.has_map ? h("a", { href: `#/environments/${environment.id}/track` }, "Track") : null,
        h("span", {}, sheetCount, " ",
          h("button", { class: "secondary", onclick: () => openFile(sheetPath(environment, Number(sheetCount.value)))
            .catch((error) => notify(error.message)) }, "Print cards")),
        h("button", { class: "secondary", onclick: async () => {
          if (!confirm(`Delete environment "${environment.name}" and its map?`)) return;
          try { await api("DELETE", `/environments/${environment.id}`); location.reload(); }
          catch (error) { notify(error.message); }
        } }, "Delete")));
  });

  const name = h("input", { name: "name", required: true, placeholder: "studio A", maxlength: 200 });
  const size = h("input", { name: "marker_size_mm", type: "number", min: 10, max: 10000, step: "any", value: 200,
                            required: true });
  const classifier = classifierSelect(null);
  const create = h("form", { class: "inline", onsubmit: async (event) => {
    event.preventDefault();
    try {
      const created = await api("POST", "/environments", {
        name: name.value.trim(), marker_size_m: Number(size.value) / 1000,
        classifier_id: classifier.value === "" ? null : Number(classifier.value),
      });
      location.hash = `#/environments/${created.id}/survey`;
    } catch (error) { notify(error.message); }
  } },
    h("label", {}, "Name", name),
    h("label", {}, "Printed card side (mm)", size),
    h("label", {}, "Classifier", classifier),
    h("button", { type: "submit" }, "Create"));

  view.append(
    h("h1", {}, "Environments"),
    environments.length ? h("table", { id: "environments" },
      h("thead", {}, h("tr", {}, ["Id", "Name", "Card side", "Map", "Classifier", ""].map((t) => h("th", {}, t)))),
      h("tbody", {}, rows))
      : h("p", { class: "muted" }, "No environment yet: create one, print its cards, film the room, survey."),
    h("h2", {}, "New environment"),
    h("p", { class: "muted" }, "Measure the printed card's side with a ruler: the map's scale comes from it."),
    create,
    h("p", { class: "muted" }, `Classifiers: ${[...classifierName.values()].join(", ")}.`));
}
