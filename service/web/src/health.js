/** "Health": the gateway's `/healthz` with the token: model, profile, precision, where scans
 * are labelled (`backend`, said in words), workers and queue depth, refreshed while the page is
 * open. */

import { el } from './dom.js';

const POLL_MS = 3000;

function workersText(workers) {
  if (!workers.length) return 'none';
  const devices = {};
  for (const worker of workers) devices[worker.device || '?'] = (devices[worker.device || '?'] || 0) + 1;
  return Object.entries(devices)
    .map(([device, n]) => `${n} on ${device}`)
    .join(', ');
}

export class HealthPanel {
  constructor(api, state) {
    this.api = api;
    this.state = state;
    this.list = document.getElementById('health');
    this.served = document.getElementById('served');
    this.timer = null;
    this.running = false;
  }

  start() {
    this.running = true;
    this.poll();
  }

  stop() {
    this.running = false;
    clearTimeout(this.timer);
  }

  async poll() {
    clearTimeout(this.timer);
    if (!this.running) return;
    try {
      const { body } = await this.api.health();
      if (body.backend) this.draw(body);
    } catch (error) {
      this.list.replaceChildren(el('dt', { text: 'status' }), el('dd', { class: 'error', text: error.message }));
    }
    if (this.running) this.timer = setTimeout(() => this.poll(), POLL_MS);
  }

  draw(health) {
    this.state.health = health;
    this.served.textContent = `${health.model || 'model'} · ${health.profile} · ${health.status}`;
    const rows = [
      ['status', health.status + (health.error ? ` (${health.error})` : '')],
      ['model', health.model || '–'],
      ['profile', health.profile],
      ['point fields', health.point_fields.join(', ')],
      ['precision', health.precision || '–'],
      ['labelled by', labelledBy(health.backend)],
      ['workers', workersText(health.workers)],
      ['queue depth', String(health.queue_depth)],
      ['batch size', String(health.batch_size)],
      ['batch wait', `${health.batch_wait_ms} ms`],
      ['checkpoint', health.checkpoint_sha256 ? health.checkpoint_sha256.slice(0, 16) : '–'],
      ['version', health.version],
    ];
    this.list.replaceChildren(
      ...rows.flatMap(([name, value]) => [
        el('dt', { text: name }),
        el('dd', { 'data-field': name, text: value }),
      ]),
    );
  }
}

/** Where the gateway labels single scans, in words (`/healthz`'s `backend`). */
function labelledBy(backend) {
  if (backend === 'local') return "the gateway's own process";
  if (backend === 'serve') return 'the Ray Serve application';
  return backend;
}
