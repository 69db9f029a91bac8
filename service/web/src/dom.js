/** Small DOM helpers: build elements without markup strings, so no text is ever parsed as HTML. */

/**
 * An element with attributes (`class`, `text`, data and ARIA attributes, event handlers as
 * `on<event>`) and children (elements or strings).
 */
export function el(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attributes)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === 'text') node.textContent = String(value);
    else if (key.startsWith('on')) node.addEventListener(key.slice(2), value);
    else if (value === true) node.setAttribute(key, '');
    else node.setAttribute(key, String(value));
  }
  for (const child of children.flat()) {
    if (child === undefined || child === null) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

const SVG = 'http://www.w3.org/2000/svg';

/** An SVG element with attributes and children. */
export function svg(tag, attributes = {}, ...children) {
  const node = document.createElementNS(SVG, tag);
  for (const [key, value] of Object.entries(attributes)) {
    if (key === 'text') node.textContent = String(value);
    else node.setAttribute(key, String(value));
  }
  for (const child of children.flat()) if (child) node.append(child);
  return node;
}

/** A colour swatch: its colour is set through the CSS object model, which the policy allows. */
export function swatch(color) {
  const node = el('span', { class: 'swatch', 'aria-hidden': 'true' });
  node.style.backgroundColor = color;
  return node;
}

/** A percentage with one decimal, from a fraction. */
export function percent(fraction) {
  return fraction === null || fraction === undefined ? '–' : (100 * fraction).toFixed(1);
}

/** A whole number with thousands separators. */
export function count(value) {
  return Number(value).toLocaleString('en-US');
}

/** Replace a table body's rows. */
export function fillBody(table, rows) {
  const body = table.tBodies[0];
  body.replaceChildren(...rows);
}

/** Save a Blob as a file through a temporary object URL. */
export function saveBlob(blob, name) {
  const url = URL.createObjectURL(blob);
  const link = el('a', { href: url, download: name });
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}
