// The service's HTTP and WebSocket API as the page uses it: one place for the base URL,
// the API key and the shape of errors.

const KEY_STORE = "fidotrack.apiKey";

/** The service's root, from the page's own address (the app is served under /app/). */
export const ROOT = new URL("..", document.baseURI).href.replace(/\/$/, "");

/** The API key: the one kept for this tab, else the one remembered on this device; "" for none. */
export function apiKey() {
  return sessionStorage.getItem(KEY_STORE) || localStorage.getItem(KEY_STORE) || "";
}

/** Whether the key is remembered on this device (kept after the tab closes). */
export function apiKeyRemembered() {
  return localStorage.getItem(KEY_STORE) !== null;
}

/**
 * Keep `key` for this tab only (sessionStorage: gone when the tab closes) or, when
 * `remember`, on this device (localStorage). "" forgets the key in both.
 */
export function setApiKey(key, remember = false) {
  sessionStorage.removeItem(KEY_STORE);
  localStorage.removeItem(KEY_STORE);
  if (key) (remember ? localStorage : sessionStorage).setItem(KEY_STORE, key);
}

/** An error the service answered with: its HTTP status and its message. */
export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

function headers(extra = {}) {
  const key = apiKey();
  return key ? { "X-API-Key": key, ...extra } : extra;
}

async function failure(response) {
  let detail = response.statusText;
  try {
    const body = await response.json();
    detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
  } catch { /* not JSON: the status text says it */ }
  return new ApiError(response.status, detail);
}

/** A JSON request; resolves to the reply's JSON (null for 204), rejects with ApiError. */
export async function api(method, path, body) {
  return (await request(method, path, body)).body;
}

/**
 * A JSON request with `extra` headers (e.g. If-Match); resolves to { body, headers }: the
 * reply's JSON (null for 204) and its headers (e.g. ETag). Rejects with ApiError.
 */
export async function request(method, path, body, extra = {}) {
  const init = { method, headers: headers(body === undefined ? extra : { "Content-Type": "application/json", ...extra }) };
  if (body !== undefined) init.body = JSON.stringify(body);
  const response = await fetch(ROOT + path, init);
  if (!response.ok) throw await failure(response);
  return { body: response.status === 204 ? null : await response.json(), headers: response.headers };
}

/** POST raw bytes (an image) and get JSON back. */
export async function postImage(path, blob) {
  const response = await fetch(ROOT + path, {
    method: "POST", body: blob, headers: headers({ "Content-Type": blob.type || "image/jpeg" }),
  });
  if (!response.ok) throw await failure(response);
  return response.json();
}

/**
 * POST a multipart form with upload progress (fetch has none): onProgress(sent, total).
 * Resolves to the reply's JSON, rejects with ApiError.
 */
export function postForm(path, form, onProgress) {
  return new Promise((resolve, reject) => {
    const request = new XMLHttpRequest();
    request.open("POST", ROOT + path);
    for (const [name, value] of Object.entries(headers())) request.setRequestHeader(name, value);
    request.upload.onprogress = (event) => onProgress(event.loaded, event.lengthComputable ? event.total : 0);
    request.onload = () => {
      let body = null;
      try { body = JSON.parse(request.responseText); } catch { /* an empty or non-JSON reply */ }
      if (request.status >= 200 && request.status < 300) resolve(body);
      else reject(new ApiError(request.status, body && typeof body.detail === "string" ? body.detail : request.statusText));
    };
    request.onerror = () => reject(new ApiError(0, "the upload failed: the connection to the service was lost"));
    request.send(form);
  });
}

/** The /track WebSocket URL of an environment, with the key in the query (browsers cannot set headers). */
export function trackUrl(environmentId) {
  const url = new URL(ROOT + "/track");
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  url.searchParams.set("environment_id", String(environmentId));
  const key = apiKey();
  if (key) url.searchParams.set("api_key", key);
  return url.href;
}

/** GET a file (a PDF sheet) with the key's header and open it in a new tab. */
export async function openFile(path) {
  const opened = window.open("", "_blank");
  const response = await fetch(ROOT + path, { headers: headers() });
  if (!response.ok) { if (opened) opened.close(); throw await failure(response); }
  const url = URL.createObjectURL(await response.blob());
  if (opened) opened.location.href = url; else location.href = url;
}
