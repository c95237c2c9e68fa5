// The single-page app: a hash router over the pages, and the state each page exposes on
// `window.fidotrack` (what is drawn, what the camera streamed) for people and tests alike.

import { apiKey, setApiKey } from "./api.js";
import { notify } from "./dom.js";
import { detectPage } from "./detect.js";
import { environmentsPage } from "./environments.js";
import { mapPage } from "./map.js";
import { surveyPage } from "./survey.js";
import { trackPage } from "./track.js";

/** Routes: a pattern of the hash and the page that draws it into the view. */
const ROUTES = [
  [/^#\/environments$/, environmentsPage],
  [/^#\/environments\/(\d+)\/survey$/, surveyPage],
  [/^#\/environments\/(\d+)\/map$/, mapPage],
  [/^#\/environments\/(\d+)\/map\/(\d+)$/, mapPage],  // the map, looking at one card
  [/^#\/environments\/(\d+)\/track$/, trackPage],
  [/^#\/detect$/, detectPage],
];

window.fidotrack = { page: null };
let leave = null;  // the current page's clean-up (stops cameras, sockets, timers)

async function route() {
  if (leave) { leave(); leave = null; }
  notify("");
  const hash = location.hash || "#/environments";
  const view = document.getElementById("view");
  for (const [pattern, page] of ROUTES) {
    const match = hash.match(pattern);
    if (!match) continue;
    view.replaceChildren();
    window.fidotrack.page = page.name;
    try {
      leave = (await page(view, ...match.slice(1).map(Number))) || null;
    } catch (error) {
      notify(error.message);
    }
    return;
  }
  location.hash = "#/environments";
}

const keyInput = document.getElementById("api-key");
keyInput.value = apiKey();
keyInput.addEventListener("change", () => { setApiKey(keyInput.value.trim()); route(); });
window.addEventListener("hashchange", route);
route();
