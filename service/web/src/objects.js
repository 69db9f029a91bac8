/**
 * The objects of a panoptic answer (`POST v1/scans?panoptic=true`): the semantic part of each
 * panoptic label, as the served profile's `panoptic` packing says, and a colour per object that
 * stays the same for an id and differs between neighbouring ids (hues a golden angle apart).
 */

const GOLDEN_ANGLE = 137.508;

/** The semantic part of each panoptic label: what a plain answer would hold for the point. */
export function semanticLabels(labels, packing) {
  const { multiplier, instance_high: instanceHigh } = packing;
  const out = new Array(labels.length);
  for (let i = 0; i < labels.length; i++) {
    out[i] = instanceHigh ? labels[i] % multiplier : Math.floor(labels[i] / multiplier);
  }
  return out;
}

/** An object's colour (RGB bytes), from its instance id. */
export function objectColor(id) {
  const hue = ((id * GOLDEN_ANGLE) % 360) / 60;
  const saturation = 0.85;
  const lightness = 0.55 + 0.1 * (id % 3 - 1);
  const chroma = (1 - Math.abs(2 * lightness - 1)) * saturation;
  const x = chroma * (1 - Math.abs((hue % 2) - 1));
  const [r, g, b] = [
    [chroma, x, 0],
    [x, chroma, 0],
    [0, chroma, x],
    [0, x, chroma],
    [x, 0, chroma],
    [chroma, 0, x],
  ][Math.floor(hue) % 6];
  const m = lightness - chroma / 2;
  return [r, g, b].map((v) => Math.round(255 * (v + m)));
}
