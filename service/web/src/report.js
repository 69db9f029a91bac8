/**
 * A job's evaluation report (`GET v1/jobs/{id}/report`) as tables with bars: overall scores, IoU
 * per class, and the same scores per sequence and per distance band. A panoptic job's report
 * (`task: "panoptic"`) is its panoptic table: PQ, SQ, RQ, PQ-dagger and mIoU overall, PQ, SQ, RQ
 * and IoU per class (things marked), and PQ and mIoU per sequence and per distance band, read from
 * either benchmark's keys (SemanticKITTI's `pq_mean`, ..., `classes`; nuScenes' `all` and a key
 * per class).
 */

import { count, el, percent, svg } from './dom.js';

const BAR_WIDTH = 160;
const BAR_HEIGHT = 12;

/** A horizontal bar for a fraction 0..1, in `color`. */
function bar(fraction, color = '#4a90d9') {
  const width = Math.max(0, Math.min(1, fraction || 0)) * BAR_WIDTH;
  return svg(
    'svg',
    {
      class: 'bar',
      width: BAR_WIDTH,
      height: BAR_HEIGHT,
      viewBox: `0 0 ${BAR_WIDTH} ${BAR_HEIGHT}`,
      role: 'img',
      'aria-label': `${percent(fraction)} %`,
    },
    svg('rect', { x: 0, y: 0, width: BAR_WIDTH, height: BAR_HEIGHT, fill: '#e6e9ee' }),
    svg('rect', { x: 0, y: 0, width: width.toFixed(1), height: BAR_HEIGHT, fill: color }),
  );
}

function table(id, caption, head, rows) {
  return el(
    'table',
    { id, class: 'numbers' },
    el('caption', { text: caption }),
    el('thead', {}, el('tr', {}, head.map((text) => el('th', { text })))),
    el('tbody', {}, rows),
  );
}

function band(part) {
  return part.max_m === null ? `${part.min_m}+ m` : `${part.min_m}-${part.max_m} m`;
}

/** The report's elements, for the job `job` of the served `profile`. */
export function reportView(report, job, profile) {
  const colors = Object.fromEntries(profile.classes.map((cls) => [cls.name, cls.color]));
  const overall = table(
    'report-overall',
    'Overall',
    ['', ''],
    [
      ['mIoU (%)', percent(report.miou)],
      ['accuracy (%)', percent(report.accuracy)],
      ['scans', count(report.num_scans)],
      ['points', count(report.num_points)],
      ['sequences', (report.sequences || []).join(' ')],
      ['profile', report.profile || profile.profile],
      ['checkpoint', (report.checkpoint_sha256 || '–').slice(0, 16)],
    ].map(([name, value]) => el('tr', {}, el('th', { text: name }), el('td', { text: value }))),
  );
  const classes = table(
    'report-classes',
    'IoU per class',
    ['class', 'IoU (%)', ''],
    Object.entries(report.iou).map(([name, iou]) =>
      el(
        'tr',
        { 'data-class': name },
        el('td', { text: name }),
        el('td', { text: percent(iou) }),
        el('td', {}, bar(iou, colors[name])),
      ),
    ),
  );
  const part = (label, scores) =>
    el(
      'tr',
      {},
      el('td', { text: label }),
      el('td', { text: count(scores.points) }),
      el('td', { text: percent(scores.miou) }),
      el('td', { text: percent(scores.accuracy) }),
      el('td', {}, bar(scores.miou)),
    );
  const sequences = table(
    'report-sequences',
    'Per sequence',
    ['sequence', 'points', 'mIoU (%)', 'accuracy (%)', 'mIoU'],
    Object.entries(report.per_sequence || {}).map(([name, scores]) => part(name, scores)),
  );
  const distance = table(
    'report-distance',
    'By distance from the sensor',
    ['band', 'points', 'mIoU (%)', 'accuracy (%)', 'mIoU'],
    (report.per_distance || []).map((scores) => part(band(scores), scores)),
  );
  return [
    el('h3', { text: `Report of job ${job.id.slice(0, 8)}` }),
    el('div', { class: 'report-tables' }, overall, classes, sequences, distance),
  ];
}

/**
 * One part of a panoptic report (overall, a sequence, a distance band) in one shape, whichever
 * benchmark's keys it has: `{pq, sq, rq, pq_dagger, miou, classes: {name: {pq, sq, rq, iou}}}`.
 */
export function panopticScores(part) {
  if (part.all) {
    const classes = {};
    for (const [name, value] of Object.entries(part)) {
      if (name !== 'all' && value && typeof value === 'object' && 'PQ' in value) {
        classes[name] = { pq: value.PQ, sq: value.SQ, rq: value.RQ, iou: value.IoU };
      }
    }
    const { PQ, SQ, RQ, mIoU, PQ_dagger: dagger } = part.all;
    return { pq: PQ, sq: SQ, rq: RQ, pq_dagger: dagger, miou: mIoU, classes };
  }
  return {
    pq: part.pq_mean,
    sq: part.sq_mean,
    rq: part.rq_mean,
    pq_dagger: part.pq_dagger,
    miou: part.iou_mean,
    classes: part.classes || {},
  };
}

/** A panoptic job's report's elements, for the job `job` of the served `profile`. */
export function panopticReportView(report, job, profile) {
  const colors = Object.fromEntries(profile.classes.map((cls) => [cls.name, cls.color]));
  const ignored = new Set(profile.classes.filter((cls) => cls.ignored).map((cls) => cls.name));
  const things = new Set((profile.panoptic && profile.panoptic.things) || []);
  const overall = panopticScores(report);
  const summary = table(
    'report-overall',
    'Overall',
    ['', ''],
    [
      ['PQ (%)', percent(overall.pq)],
      ['SQ (%)', percent(overall.sq)],
      ['RQ (%)', percent(overall.rq)],
      ['PQ† (%)', percent(overall.pq_dagger)],
      ['mIoU (%)', percent(overall.miou)],
      ['scans', count(report.num_scans)],
      ['points', count(report.num_points)],
      ['sequences', (report.sequences || []).join(' ')],
      ['benchmark', report.benchmark],
      ['profile', report.profile || profile.profile],
      ['checkpoint', (report.checkpoint_sha256 || '–').slice(0, 16)],
    ].map(([name, value]) => el('tr', {}, el('th', { text: name }), el('td', { text: value }))),
  );
  const classes = table(
    'report-classes',
    'Panoptic quality per class',
    ['class', 'PQ (%)', 'SQ (%)', 'RQ (%)', 'IoU (%)', 'PQ'],
    Object.entries(overall.classes)
      .filter(([name]) => !ignored.has(name))
      .map(([name, scores]) =>
        el(
          'tr',
          { 'data-class': name, 'data-thing': things.has(name) ? 'true' : 'false' },
          el('td', { text: things.has(name) ? `${name} (thing)` : name }),
          el('td', { text: percent(scores.pq) }),
          el('td', { text: percent(scores.sq) }),
          el('td', { text: percent(scores.rq) }),
          el('td', { text: percent(scores.iou) }),
          el('td', {}, bar(scores.pq, colors[name])),
        ),
      ),
  );
  const part = (label, scores) =>
    el(
      'tr',
      {},
      el('td', { text: label }),
      el('td', { text: percent(scores.pq) }),
      el('td', { text: percent(scores.miou) }),
      el('td', {}, bar(scores.pq)),
    );
  const sequences = table(
    'report-sequences',
    'Per sequence',
    ['sequence', 'PQ (%)', 'mIoU (%)', 'PQ'],
    Object.entries(report.per_sequence || {}).map(([name, scores]) =>
      part(name, panopticScores(scores)),
    ),
  );
  const distance = table(
    'report-distance',
    'By distance from the sensor',
    ['band', 'PQ (%)', 'mIoU (%)', 'PQ'],
    (report.per_distance || []).map((scores) => part(band(scores), panopticScores(scores))),
  );
  return [
    el('h3', { text: `Panoptic report of job ${job.id.slice(0, 8)}` }),
    el('div', { class: 'report-tables' }, summary, classes, sequences, distance),
  ];
}
