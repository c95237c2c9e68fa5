// Small helpers to build the pages' DOM without a framework.

/**
 * An element with attributes (on* keys become listeners) and children. `style` is set
 * through the element's style object: the page's Content-Security-Policy refuses style
 * attributes.
 */
export function h(tag, attributes = {}, ...children) {
  const element = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) {
    if (value === undefined || value === null || value === false) continue;
    if (name.startsWith("on")) element.addEventListener(name.slice(2), value);
    else if (name === "style") element.style.cssText = value;
    else if (value === true) element.setAttribute(name, "");
    else element.setAttribute(name, value);
  }
  element.append(...children.flat().filter((c) => c !== null && c !== undefined));
  return element;
}

/** A number with a fixed count of decimals, or a dash. */
export function fixed(value, digits = 1) {
  return Number.isFinite(value) ? value.toFixed(digits) : "–";
}

/** The q-quantile (0..1) of numbers, nearest rank; NaN when there are none. */
export function quantile(values, q) {
  if (values.length === 0) return NaN;
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.min(sorted.length - 1, Math.max(0, Math.ceil(q * sorted.length) - 1))];
}

/** Show a message in the notice bar (an error the service gave, say); "" hides it. */
export function notify(message) {
  const notice = document.getElementById("notice");
  notice.textContent = message || "";
  notice.hidden = !message;
}

/**
 * One detected target on a 2D canvas: the quadrilateral of its discs in `colour`, and its
 * id in white on a dark box at its centre, in `size`-pixel text.
 */
export function drawTarget(g, target, colour, size) {
  g.strokeStyle = colour;
  g.beginPath();
  target.discs.forEach(([u, v], i) => (i ? g.lineTo(u, v) : g.moveTo(u, v)));
  g.closePath();
  g.stroke();
  const [cu, cv] = target.discs.reduce(([a, b], [u, v]) => [a + u / 4, b + v / 4], [0, 0]);
  g.font = `bold ${size}px sans-serif`;
  g.fillStyle = "#000";
  g.fillRect(cu - 0.875 * size, cv - 0.6875 * size, 1.75 * size, 1.375 * size);
  g.fillStyle = "#fff"; g.textAlign = "center"; g.textBaseline = "middle"; g.fillText(String(target.id), cu, cv);
}
