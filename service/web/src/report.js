/**
 * A job's evaluation report (`GET v1/jobs/{id}/report`) as tables with bars: overall scores, IoU
 * per class, and the same scores per sequence and per distance band.
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
