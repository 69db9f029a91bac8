/**
 * Labels to classes and the benchmark's scores, computed in the page from the served profile
 * (`GET v1/profile`): raw ids are masked to their low 16 bits and mapped through the profile's
 * learning map (ids it does not list are the unlabeled class); C[pred][gt] with the columns of
 * ignored ground-truth classes zeroed; IoU = TP / (TP + FP + FN); mIoU averages every evaluated
 * class (an absent class counts 0); accuracy = TP / (TP + FP) over the evaluated classes.
 */

const EPS = 1e-15;

/** A table from every 16-bit raw id to its class index. */
export function classLookup(profile) {
  const lookup = new Uint8Array(65536).fill(profile.unlabeled_class);
  for (const [raw, cls] of Object.entries(profile.raw_to_class)) lookup[Number(raw)] = cls;
  return lookup;
}

/** The class index (Uint8Array) of every raw label. */
export function toClasses(raw, lookup) {
  const classes = new Uint8Array(raw.length);
  for (let i = 0; i < raw.length; i++) classes[i] = lookup[raw[i] & 0xffff];
  return classes;
}

/** Points per class index. */
export function histogram(classes, numClasses) {
  const counts = new Array(numClasses).fill(0);
  for (let i = 0; i < classes.length; i++) counts[classes[i]]++;
  return counts;
}

/** Points per class name, for the classes present. */
export function classCounts(classes, profile) {
  const counts = histogram(classes, profile.classes.length);
  const named = {};
  profile.classes.forEach((cls, index) => {
    if (counts[index]) named[cls.name] = counts[index];
  });
  return named;
}

/** IoU by evaluated class name, mIoU, accuracy and the points scored, as the benchmark counts. */
export function scores(predicted, truth, profile) {
  const n = profile.classes.length;
  const confusion = new Float64Array(n * n);
  for (let i = 0; i < predicted.length; i++) confusion[predicted[i] * n + truth[i]]++;
  const ignored = profile.classes.map((cls) => cls.ignored);
  const tp = new Array(n).fill(0);
  const fp = new Array(n).fill(0);
  const fn = new Array(n).fill(0);
  let points = 0;
  for (let p = 0; p < n; p++) {
    for (let g = 0; g < n; g++) {
      if (ignored[g]) continue;
      const value = confusion[p * n + g];
      points += value;
      if (p === g) tp[p] += value;
      else {
        fp[p] += value;
        fn[g] += value;
      }
    }
  }
  const iou = {};
  let sum = 0;
  let evaluated = 0;
  let hits = 0;
  let predictedEvaluated = 0;
  profile.classes.forEach((cls, c) => {
    if (cls.ignored) return;
    iou[cls.name] = tp[c] / (tp[c] + fp[c] + fn[c] + EPS);
    sum += iou[cls.name];
    evaluated += 1;
    hits += tp[c];
    predictedEvaluated += tp[c] + fp[c];
  });
  return {
    iou,
    miou: evaluated ? sum / evaluated : 0,
    accuracy: hits / (predictedEvaluated + EPS),
    points,
  };
}
