// The single-page app: a hash router over the pages, and the state each page exposes on
// `window.fidotrack` (what is drawn, what the camera streamed) for people and tests alike.

import { apiKey, apiKeyRemembered, setApiKey } from "./api.js";
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

// The key is kept for this tab unless "remember on this device" is ticked; forgetting it
// clears it from both stores.
const keyInput = document.getElementById("api-key");
const rememberKey = document.getElementById("remember-key");
const forgetKey = document.getElementById("forget-key");
function keepKey() {
  setApiKey(keyInput.value.trim(), rememberKey.checked);
  forgetKey.hidden = !apiKey();
}
keyInput.value = apiKey();
rememberKey.checked = apiKeyRemembered();
forgetKey.hidden = !apiKey();
keyInput.addEventListener("change", () => { keepKey(); route(); });
rememberKey.addEventListener("change", keepKey);
forgetKey.addEventListener("click", () => {
  keyInput.value = "";
  rememberKey.checked = false;
  keepKey();
  route();
});
window.addEventListener("hashchange", route);
route();
